"""What a service process serves, and what the processes without a model load."""

import subprocess
import sys

import pytest

from services.runtime import run_service
from services.stack import Stack, StackConfig
from shared.settings import SHIPPED_MODEL, Settings


def test_the_router_and_the_gateway_do_not_load_torch():
    """torch costs a process about 200 MB; only the model services need it."""
    code = (
        "import sys, services.cli, services.cli.serve, services.serve, services.gateway.app; "
        "sys.exit('torch' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_one_process_serves_a_task_once():
    with pytest.raises(ValueError, match="same task"):
        run_service("encoder", lambda _: {}, Settings(), [SHIPPED_MODEL, SHIPPED_MODEL])


def test_encoder_replicas_are_named_apart_and_at_least_one(monkeypatch):
    started = []
    monkeypatch.setattr(Stack, "start_router", lambda self: None)
    monkeypatch.setattr(Stack, "_wait_for_router", lambda self: None)
    monkeypatch.setattr(Stack, "start_gateway", lambda self: None)
    monkeypatch.setattr(
        Stack, "start_service", lambda self, service, name=None, model=None: started.append(name)
    )
    Stack(StackConfig(models=(SHIPPED_MODEL,), encoders=3)).start()
    assert started == ["encoder", "encoder-2", "encoder-3", "planner", "apn", "sim"]
    started.clear()
    Stack(StackConfig(models=(SHIPPED_MODEL,), encoders=2, process_per_task=True)).start()
    assert started[:2] == ["encoder-box_stacking", "encoder-box_stacking-2"]
    with pytest.raises(ValueError, match="encoders must be at least 1"):
        StackConfig(models=(SHIPPED_MODEL,), encoders=0)

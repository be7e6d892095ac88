"""What a service process serves, and what the processes without a model load."""

import subprocess
import sys

import pytest

from services.runtime import run_service
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

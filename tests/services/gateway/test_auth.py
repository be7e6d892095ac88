"""REST API keys over real HTTP: opt-in, Bearer keys checked against digests, never logged."""

from __future__ import annotations

import logging

import httpx
import pytest

from services.gateway.app import create_app
from services.gateway.auth import digest, load_digests, main
from shared.settings import Settings

KEY = "k3y-from-env_0123456789"
FILE_KEY = "another-key-from-the-file"


@pytest.fixture(scope="module")
def keys_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("keys") / "api_keys"
    path.write_text(f"# who holds which key\nsha256:{digest(FILE_KEY)}  robot fleet\n\n")
    return path


@pytest.fixture(scope="module")
def locked(gateway_with, keys_file):
    yield from gateway_with(api_key_hashes=digest(KEY), api_keys_file=keys_file)


def get(url: str, path: str, key: str | None = None) -> httpx.Response:
    headers = {} if key is None else {"Authorization": f"Bearer {key}"}
    return httpx.get(url + path, headers=headers, timeout=10)


def test_requests_without_a_known_key_get_401_and_health_stays_open(locked):
    assert get(locked, "/tasks/box_stacking").status_code == 401
    assert get(locked, "/tasks/box_stacking", "wrong").status_code == 401
    reply = httpx.post(locked + "/plan", json={}, headers={"Authorization": f"Basic {KEY}"})
    assert reply.status_code == 401 and reply.headers["www-authenticate"].startswith("Bearer")
    assert get(locked, "/health").status_code in (200, 503)  # open: no services here, so 503
    assert get(locked, "/tasks/box_stacking", KEY).status_code == 200
    assert get(locked, "/tasks/box_stacking", FILE_KEY).status_code == 200


def test_keys_are_off_unless_configured(live_gateway):
    assert get(live_gateway.url, "/tasks/box_stacking").status_code == 200


def test_keys_never_reach_a_log(locked, caplog):
    with caplog.at_level(logging.DEBUG):
        for key in (KEY, "wrong-key-xyz", None):
            get(locked, "/tasks/box_stacking", key)
            httpx.post(
                locked + "/plan", json={"task": key}, headers={"Authorization": f"Bearer {key}"}
            )
    text = caplog.text
    assert KEY not in text and "wrong-key-xyz" not in text


def test_a_keys_file_entry_that_is_not_a_digest_is_refused_without_showing_it(tmp_path):
    path = tmp_path / "keys"
    path.write_text("plain-secret-key\n")
    with pytest.raises(ValueError, match="entry 1: not a sha256 digest") as info:
        load_digests("", path)
    assert "plain-secret-key" not in str(info.value)
    assert load_digests("", None) == frozenset()  # nothing configured: keys are off


def test_new_prints_a_key_and_its_digest(capsys):
    assert main(["new"]) == 0
    key_line, digest_line = capsys.readouterr().out.splitlines()
    key = key_line.rsplit(" ", 1)[1]
    assert digest_line.endswith(f"sha256:{digest(key)}") and len(key) >= 40


def test_a_deployment_that_requires_keys_refuses_to_start_without_any(router_endpoint):
    with pytest.raises(ValueError, match="LSR_REQUIRE_API_KEYS"):
        create_app(Settings(zenoh_connect=router_endpoint, require_api_keys=True))
    assert create_app(Settings(require_api_keys=True, api_key_hashes=digest(KEY)))

"""The Kubernetes manifests (deploy/k8s), checked offline: written by shared.k8s, valid against
the Kubernetes schemas (kubernetes-validate ships them), and wired as docker-compose.yml is."""

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from ruamel.yaml import YAML

from shared import k8s
from shared.zenoh_access import write_deployment

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy" / "k8s"


def validate(*paths: Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "kubernetes_validate", "--strict", "--quiet"]
    return subprocess.run([*command, *map(str, paths)], capture_output=True, text=True, timeout=120)


def resources() -> dict[tuple[str, str], dict[str, Any]]:
    """(kind, name) -> the resource, over every committed file."""
    found = {}
    for path in sorted(DEPLOY.glob("*.yaml")):
        for doc in YAML(typ="safe").load_all(path.read_text()):
            found[(doc["kind"], doc["metadata"]["name"])] = doc
    return found


def container(resource: dict[str, Any]) -> dict[str, Any]:
    (only,) = resource["spec"]["template"]["spec"]["containers"]
    return only


def env(resource: dict[str, Any]) -> dict[str, str]:
    return {e["name"]: e["value"] for e in container(resource)["env"]}


def test_the_committed_manifests_are_what_the_generator_writes(tmp_path: Path) -> None:
    written = {p.name: p.read_text() for p in k8s.write(tmp_path)}
    committed = {p.name: p.read_text() for p in DEPLOY.glob("*.yaml")}
    assert written == committed, "run `python -m shared.k8s --out deploy/k8s`"


def test_every_manifest_is_valid_against_the_kubernetes_schemas() -> None:
    result = validate(*sorted(DEPLOY.glob("*.yaml")))
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_validator_rejects_a_broken_manifest(tmp_path: Path) -> None:
    broken = tmp_path / "broken.yaml"
    text = (DEPLOY / "gateway.yaml").read_text().replace("replicas: 1", "replicas: one", 1)
    broken.write_text(text.replace("containerPort:", "containerPorts:", 1))
    result = validate(broken)
    assert result.returncode != 0 and "gateway" in result.stdout + result.stderr


def test_the_router_is_a_stateful_set_behind_the_name_everyone_connects_to() -> None:
    found = resources()
    router = found[("StatefulSet", k8s.ROUTER)]
    assert router["spec"]["serviceName"] == k8s.ROUTER
    assert found[("Service", k8s.ROUTER)]["spec"]["clusterIP"] == "None"
    args = container(router)["args"]
    assert "--no-multicast-scouting" in args and args[args.index("--config") + 1].endswith(
        "/router.json5"
    )
    for (kind, _), resource in found.items():
        if kind == "Deployment":
            assert env(resource)["LSR_ZENOH_CONNECT"] == f"tcp/{k8s.ROUTER}:{k8s.ZENOH_PORT}"


@pytest.mark.parametrize("task", k8s.TASKS)
@pytest.mark.parametrize("role", ["encoder", "planner", "apn", "sim"])
def test_a_model_service_mounts_its_model_read_only_and_only_its_own_credentials(
    role: str, task: str
) -> None:
    deployment = resources()[("Deployment", f"{task.replace('_', '-')}-{role}")]
    spec = deployment["spec"]["template"]["spec"]
    box = container(deployment)
    variables = env(deployment)
    assert box["command"] == ["lsr", "serve", role]
    assert variables["LSR_REQUIRE_SEALED_MODEL"] == "true"
    mounts = {m["name"]: m for m in box["volumeMounts"]}
    assert mounts["models"]["readOnly"] and mounts["models"]["subPath"] == task
    assert variables["LSR_MODEL_DIR"] == mounts["models"]["mountPath"]
    volumes = {v["name"]: v for v in spec["volumes"]}
    assert volumes["models"]["persistentVolumeClaim"]["readOnly"]
    items = volumes["zenoh"]["secret"]["items"]
    assert [i["key"] for i in items] == [f"{role}.json5"]  # no other role's password
    assert variables["LSR_ZENOH_CONFIG"] == f"{mounts['zenoh']['mountPath']}/{role}.json5"
    assert box["livenessProbe"]["exec"]["command"] == ["lsr", "ping", role, "--this-host"]


def test_the_gateway_serves_every_task_with_keys_and_records_experience() -> None:
    found = resources()
    gateway = found[("Deployment", "gateway")]
    variables = env(gateway)
    assert YAML(typ="safe").load(variables["LSR_TASKS"]) == list(k8s.TASKS)
    assert variables["LSR_REQUIRE_API_KEYS"] == "true"
    mounts = {m["name"]: m["mountPath"] for m in container(gateway)["volumeMounts"]}
    assert variables["LSR_API_KEYS_FILE"] == f"{mounts['keys']}/api_keys.sha256"
    assert variables["LSR_EXPERIENCE_DIR"] == mounts["experience"]
    assert found[("Service", "gateway")]["spec"]["ports"][0]["port"] == k8s.GATEWAY_PORT
    for task in k8s.TASKS:
        for role in ("encoder", "planner", "apn", "sim"):
            assert ("Deployment", f"{task.replace('_', '-')}-{role}") in found


def test_the_secret_holds_the_files_the_access_generator_writes(tmp_path: Path) -> None:
    written = write_deployment(
        tmp_path, robots=[], dictionary_at=f"{k8s.SECRETS_AT}/users.txt", files_at=k8s.SECRETS_AT
    )
    assert f"{k8s.SECRETS_AT}/users.txt" in written["router"].read_text()
    keys = {
        item["key"]
        for (kind, _), resource in resources().items()
        if kind in ("Deployment", "StatefulSet")
        for volume in resource["spec"]["template"]["spec"]["volumes"]
        if "secret" in volume and volume["secret"]["secretName"] == k8s.ZENOH_SECRET
        for item in volume["secret"]["items"]
    }
    assert keys <= {p.name for p in tmp_path.iterdir()}

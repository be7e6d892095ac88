"""The deployment files, checked without a docker engine: docker-compose.yml against the compose
specification and the wiring the services expect; the Dockerfile against the Makefile's install."""

import json
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from ruamel.yaml import YAML

from shared.settings import shipped_models
from shared.zenoh_access import write_deployment

ROOT = Path(__file__).resolve().parents[1]
MODEL_SERVICES = ("encoder", "planner", "apn", "sim")
# Compose service name -> (service it runs, task whose model it mounts): four for each task.
TASK_SERVICES = {
    f"{prefix}{name}": (name, task)
    for prefix, task in (
        ("", "box_stacking"),
        ("cloth-", "cloth_folding"),
        ("tshirt-", "tshirt_folding"),
        ("rope-", "rope_box"),
    )
    for name in MODEL_SERVICES
}
SERVICES = (*MODEL_SERVICES, "gateway")
OPTIONS_WITH_VALUE = {"--index-url", "-i", "--extra-index-url"}


def compose_services() -> dict[str, Any]:
    return YAML(typ="safe").load((ROOT / "docker-compose.yml").read_text())["services"]


def pinned(name: str) -> str:
    """The version pyproject.toml pins `name` to."""
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    return next(dep.split("==")[1] for dep in deps if dep.split("==")[0] == name)


def validate(path: Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "check_jsonschema", "--builtin-schema", "vendor.compose-spec"]
    return subprocess.run([*command, str(path)], capture_output=True, text=True, timeout=120)


def setting(service: dict[str, Any], flag: str, variable: str) -> str | None:
    """A CLI setting, from the command's flag or else from the environment."""
    command = service["command"]
    if flag in command:
        return command[command.index(flag) + 1]
    return service.get("environment", {}).get(variable)


def pip_installs(commands: list[str]) -> list[list[str]]:
    """What each `pip install` in `commands` installs, in order: the requirements without options
    (index, quiet, editable), pip's path, quotes or the local project's extras."""
    installs = []
    for line in commands:
        for command in re.split(r"&&|\|\||;", line):
            words = shlex.split(command)
            starts = [i for i, w in enumerate(words[:-1]) if Path(w).name == "pip"]
            if not starts or words[starts[0] + 1] != "install":
                continue
            requirements, skip = [], False
            for word in words[starts[0] + 2 :]:
                if skip:
                    skip = False
                elif word.startswith("-"):
                    skip = word in OPTIONS_WITH_VALUE
                else:
                    requirements.append(re.sub(r"\[.*\]$", "", word) if word[0] in "./" else word)
            installs.append(requirements)
    return installs


def test_compose_file_follows_the_compose_specification() -> None:
    result = validate(ROOT / "docker-compose.yml")
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_validator_rejects_a_broken_compose_file(tmp_path: Path) -> None:
    broken = tmp_path / "docker-compose.yml"
    broken.write_text('services: {x: {image: 5, ports: "bad"}}\n')
    assert validate(broken).returncode == 1


def test_router_is_the_python_packages_zenoh_without_multicast() -> None:
    router = compose_services()["zenohd"]
    assert router["image"] == f"eclipse/zenoh:{pinned('eclipse-zenoh')}"
    assert "--no-multicast-scouting" in router["command"]


@pytest.mark.parametrize("name", [*TASK_SERVICES, "gateway"])
def test_service_runs_the_project_image_on_the_router(name: str) -> None:
    service = compose_services()[name]
    runs = TASK_SERVICES.get(name, (name, None))[0]
    build = service["build"]
    context = ROOT / (build if isinstance(build, str) else build["context"])
    dockerfile = "Dockerfile" if isinstance(build, str) else build.get("dockerfile", "Dockerfile")
    assert (context / dockerfile).resolve() == ROOT / "Dockerfile"
    assert service["command"][:3] == ["lsr", "serve", runs]
    assert setting(service, "--connect", "LSR_ZENOH_CONNECT") == "tcp/zenohd:7447"
    assert "zenohd" in service["depends_on"]
    assert service["healthcheck"]["test"][0] == "CMD"
    assert "container_name" not in service  # `docker compose up --scale NAME=N` needs that


@pytest.mark.parametrize("name", TASK_SERVICES)
def test_model_service_mounts_its_tasks_model_read_only(name: str) -> None:
    service = compose_services()[name]
    runs, task = TASK_SERVICES[name]
    model_dir = f"/models/{task}"
    assert setting(service, "--model", "LSR_MODEL_DIR") == model_dir
    mount = next(v for v in service["volumes"] if v["target"] == model_dir)
    assert mount["read_only"] is True
    assert (ROOT / mount["source"]).resolve() == ROOT / "models" / task
    assert service["healthcheck"]["test"] == ["CMD", "lsr", "ping", runs, "--this-host"]


def test_gateway_serves_every_shipped_model_and_each_has_services() -> None:
    services = compose_services()
    served = json.loads(services["gateway"]["environment"]["LSR_TASKS"])
    assert sorted(served) == sorted({task for _, task in TASK_SERVICES.values()})
    assert sorted(served) == sorted(p.name for p in shipped_models())


def test_gateway_records_experience_on_a_volume_of_its_own() -> None:
    gateway = compose_services()["gateway"]
    folder = gateway["environment"]["LSR_EXPERIENCE_DIR"]
    assert f"experience:{folder}" in gateway["volumes"]
    compose = YAML(typ="safe").load((ROOT / "docker-compose.yml").read_text())
    assert "experience" in compose["volumes"]


def test_gateway_publishes_port_8000() -> None:
    gateway = compose_services()["gateway"]
    assert setting(gateway, "--host", "LSR_HOST") == "0.0.0.0"  # not the default, loopback
    assert setting(gateway, "--port", "LSR_PORT") == "8000"
    assert [str(port).rsplit(":", 1)[-1] for port in gateway["ports"]] == ["8000"]
    assert "http://127.0.0.1:8000/health" in gateway["healthcheck"]["test"][-1]


def test_dockerfile_installs_what_the_makefile_installs() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    runs = [line[4:] for line in dockerfile.splitlines() if line.startswith("RUN ")]
    makefile = (ROOT / "Makefile").read_text().replace("\\\n", " ")
    recipes = [line for line in makefile.splitlines() if re.match(r"\t\s*[^#\s]", line)]
    assert pip_installs(runs) == pip_installs(recipes)
    assert pip_installs(runs) == [["pip"], [f"torch=={pinned('torch')}"], ["."]]
    # torch's CPU build: PyPI's linux wheel pulls CUDA.
    assert re.search(r'--index-url "?\$\{?TORCH_INDEX_URL\b.* torch==', dockerfile)


def test_gateway_requires_api_keys_from_a_mounted_digest_file() -> None:
    gateway = compose_services()["gateway"]
    assert gateway["environment"]["LSR_REQUIRE_API_KEYS"] == "true"
    assert gateway["environment"]["LSR_API_KEYS_FILE"] == "/run/secrets/lsr_api_keys"
    secrets = YAML(typ="safe").load((ROOT / "docker-compose.yml").read_text())["secrets"]
    assert (ROOT / secrets["lsr_api_keys"]["file"]).is_file()


def test_every_process_joins_the_bus_with_its_own_generated_credentials(tmp_path: Path) -> None:
    compose = YAML(typ="safe").load((ROOT / "docker-compose.yml").read_text())
    services, secrets = compose["services"], compose["secrets"]
    router = services["zenohd"]
    config = router["command"][router["command"].index("--config") + 1]
    assert config == "/run/secrets/zenoh_router" and set(router["secrets"]) >= {"zenoh_router"}
    written = write_deployment(tmp_path, robots=[], dictionary_at="/run/secrets/zenoh_users")
    assert "/run/secrets/zenoh_users" in written["router"].read_text()
    files = {name: Path(secret["file"]).name for name, secret in secrets.items()}
    assert files["zenoh_router"] == "router.json5" and files["zenoh_users"] == "users.txt"
    for name in [*TASK_SERVICES, "gateway"]:
        role = TASK_SERVICES.get(name, (name, None))[0]  # a role per service, whatever its task
        env = services[name]["environment"]
        assert env["LSR_ZENOH_CONFIG"] == f"/run/secrets/zenoh_{role}"
        assert f"zenoh_{role}" in services[name]["secrets"]
        assert files[f"zenoh_{role}"] == written[role].name  # the generator writes that name


@pytest.mark.parametrize("name", TASK_SERVICES)
def test_model_services_refuse_an_unsealed_model(name: str) -> None:
    assert compose_services()[name]["environment"]["LSR_REQUIRE_SEALED_MODEL"] == "true"

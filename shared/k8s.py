"""Kubernetes manifests for the stack, written from the same roles and tasks as docker-compose.yml.

  python -m shared.k8s --out deploy/k8s            # what deploy/k8s holds (a test checks it)
  python -m shared.zenoh_access --out deploy/zenoh --robots arm-1 \
      --dictionary-at /run/secrets/zenoh/users.txt --files-at /run/secrets/zenoh
  kubectl create secret generic lsr-zenoh --from-file=deploy/zenoh/
  kubectl create secret generic lsr-api-keys --from-file=api_keys.sha256=deploy/api_keys.sha256
  kubectl apply -f deploy/k8s/

The router is a StatefulSet (a stable name the others connect to); each task's four model
services and the gateway are Deployments with the health checks of the compose file; the model
folders come read-only from one volume claim (`lsr-models`, a folder a task, as `models/`),
keys and zenoh credentials from secrets, each process mounting only its own role's file.
Scale a service with `kubectl scale deployment/box-stacking-planner --replicas=3`: replicas
serve the same zenoh keys and the callers spread over them (docs/services.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML

from shared.settings import shipped_models
from shared.zenoh_access import SERVICE_ROLES

IMAGE = "lsr:local"  # the Dockerfile's image; push it to a registry the cluster pulls from
IMAGE_UID = 10001  # the Dockerfile's user
ZENOH_IMAGE = "eclipse/zenoh:1.10.2"  # the router; its version is pyproject.toml's pin
ROUTER = "zenoh-router"
ZENOH_PORT = 7447
GATEWAY_PORT = 8000
TASKS = tuple(p.name for p in shipped_models())  # the tasks with a model to serve, a folder each
MODELS_CLAIM = "lsr-models"
EXPERIENCE_CLAIM = "lsr-experience"
ZENOH_SECRET = "lsr-zenoh"
KEYS_SECRET = "lsr-api-keys"
SECRETS_AT = "/run/secrets/zenoh"
LABEL = "app.kubernetes.io/name"


def _probes(
    check: dict[str, Any], start_s: int, live: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Readiness and liveness (`live`, default `check`) as the compose health check (every
    30 s, 3 tries), after a start of up to `start_s` seconds (importing torch, loading a model)."""
    live = live or check
    return {
        "startupProbe": {**live, "periodSeconds": 10, "failureThreshold": start_s // 10},
        "readinessProbe": {**check, "periodSeconds": 30, "timeoutSeconds": 10},
        "livenessProbe": {**live, "periodSeconds": 30, "timeoutSeconds": 10, "failureThreshold": 3},
    }


def _zenoh_file(role: str) -> dict[str, Any]:
    """The volume holding only this role's credentials (and the CA, where links are TLS)."""
    items = [{"key": f"{role}.json5", "path": f"{role}.json5"}]
    return {"name": "zenoh", "secret": {"secretName": ZENOH_SECRET, "items": items}}


def _deployment(
    name: str,
    container: dict[str, Any],
    volumes: list[dict[str, Any]],
    replicas: int = 1,
) -> dict[str, Any]:
    labels = {LABEL: name, "app.kubernetes.io/part-of": "lsr"}
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {"name": name, "labels": labels},
        "spec": {
            "replicas": replicas,
            "selector": {"matchLabels": {LABEL: name}},
            "template": {
                "metadata": {"labels": labels},
                "spec": {
                    "automountServiceAccountToken": False,
                    "securityContext": {"runAsNonRoot": True, "runAsUser": IMAGE_UID},
                    "containers": [container],
                    "volumes": volumes,
                },
            },
        },
    }


def _env(**values: str) -> list[dict[str, str]]:
    return [{"name": k, "value": v} for k, v in values.items()]


def model_service(role: str, task: str) -> dict[str, Any]:
    """One task's encoder, planner, APN or sim: its model folder read-only, its credentials."""
    name = f"{task.replace('_', '-')}-{role}"
    container = {
        "name": role,
        "image": IMAGE,
        "command": ["lsr", "serve", role],
        "env": _env(
            LSR_ZENOH_CONNECT=f"tcp/{ROUTER}:{ZENOH_PORT}",
            LSR_MODEL_DIR=f"/models/{task}",
            LSR_REQUIRE_SEALED_MODEL="true",
            LSR_ZENOH_CONFIG=f"{SECRETS_AT}/{role}.json5",
            OMP_NUM_THREADS="1",  # one torch thread a replica: scale with replicas instead
        ),
        "resources": {"requests": {"cpu": "1", "memory": "512Mi"}},
        "volumeMounts": [
            {"name": "models", "mountPath": f"/models/{task}", "subPath": task, "readOnly": True},
            {"name": "zenoh", "mountPath": SECRETS_AT, "readOnly": True},
        ],
        **_probes({"exec": {"command": ["lsr", "ping", role, "--this-host"]}}, 120),
    }
    models = {
        "name": "models",
        "persistentVolumeClaim": {"claimName": MODELS_CLAIM, "readOnly": True},
    }
    return _deployment(name, container, [models, _zenoh_file(role)])


def gateway() -> dict[str, Any]:
    container = {
        "name": "gateway",
        "image": IMAGE,
        "command": ["lsr", "serve", "gateway"],
        "env": _env(
            LSR_ZENOH_CONNECT=f"tcp/{ROUTER}:{ZENOH_PORT}",
            LSR_HOST="0.0.0.0",
            LSR_PORT=str(GATEWAY_PORT),
            LSR_TASKS="[" + ", ".join(f'"{t}"' for t in TASKS) + "]",
            LSR_REQUIRE_API_KEYS="true",
            LSR_API_KEYS_FILE="/run/secrets/lsr/api_keys.sha256",
            LSR_ZENOH_CONFIG=f"{SECRETS_AT}/gateway.json5",
            LSR_EXPERIENCE_DIR="/experience",
        ),
        "ports": [{"name": "http", "containerPort": GATEWAY_PORT}],
        "resources": {"requests": {"cpu": "1", "memory": "512Mi"}},
        "volumeMounts": [
            {"name": "keys", "mountPath": "/run/secrets/lsr", "readOnly": True},
            {"name": "zenoh", "mountPath": SECRETS_AT, "readOnly": True},
            {"name": "experience", "mountPath": "/experience"},
        ],
        # Ready while it answers HTTP; alive while it listens. Not /health: that is 503 while
        # any task's service is missing, and the gateway should then say so (503 by name), not
        # drop out of the Service or be restarted.
        **_probes(
            {"httpGet": {"path": "/tasks", "port": "http"}}, 30, {"tcpSocket": {"port": "http"}}
        ),
    }
    volumes = [
        {"name": "keys", "secret": {"secretName": KEYS_SECRET}},
        _zenoh_file("gateway"),
        {"name": "experience", "persistentVolumeClaim": {"claimName": EXPERIENCE_CLAIM}},
    ]
    return _deployment("gateway", container, volumes)


def _service(name: str, port: int, target: str | int, headless: bool = False) -> dict[str, Any]:
    spec: dict[str, Any] = {
        "selector": {LABEL: name},
        "ports": [{"name": "main", "port": port, "targetPort": target}],
    }
    if headless:
        spec["clusterIP"] = "None"
    return {"apiVersion": "v1", "kind": "Service", "metadata": {"name": name}, "spec": spec}


def router() -> list[dict[str, Any]]:
    """The router as a StatefulSet behind a headless Service: clients connect to its name."""
    labels = {LABEL: ROUTER, "app.kubernetes.io/part-of": "lsr"}
    check = {"tcpSocket": {"port": ZENOH_PORT}}
    container = {
        "name": "router",
        "image": ZENOH_IMAGE,
        "args": [
            "--config",
            f"{SECRETS_AT}/router.json5",
            "--no-multicast-scouting",
            "-l",
            f"tcp/0.0.0.0:{ZENOH_PORT}",
            "--rest-http-port",
            "none",
        ],
        "ports": [{"name": "zenoh", "containerPort": ZENOH_PORT}],
        "resources": {"requests": {"cpu": "500m", "memory": "128Mi"}},
        "volumeMounts": [{"name": "zenoh", "mountPath": SECRETS_AT, "readOnly": True}],
        **_probes(check, 30),
    }
    items = [{"key": k, "path": k} for k in ("router.json5", "users.txt")]
    return [
        _service(ROUTER, ZENOH_PORT, "zenoh", headless=True),
        {
            "apiVersion": "apps/v1",
            "kind": "StatefulSet",
            "metadata": {"name": ROUTER, "labels": labels},
            "spec": {
                "serviceName": ROUTER,
                "replicas": 1,
                "selector": {"matchLabels": {LABEL: ROUTER}},
                "template": {
                    "metadata": {"labels": labels},
                    "spec": {
                        "automountServiceAccountToken": False,
                        "containers": [container],
                        "volumes": [
                            {
                                "name": "zenoh",
                                "secret": {"secretName": ZENOH_SECRET, "items": items},
                            }
                        ],
                    },
                },
            },
        },
    ]


def claims() -> list[dict[str, Any]]:
    """The models (written once by whoever trains them, read-only to the services) and the
    gateway's experience folder."""

    def claim(name: str, mode: str, size: str) -> dict[str, Any]:
        return {
            "apiVersion": "v1",
            "kind": "PersistentVolumeClaim",
            "metadata": {"name": name},
            "spec": {"accessModes": [mode], "resources": {"requests": {"storage": size}}},
        }

    return [
        claim(MODELS_CLAIM, "ReadOnlyMany", "1Gi"),
        claim(EXPERIENCE_CLAIM, "ReadWriteOnce", "5Gi"),
    ]


def manifests() -> dict[str, list[dict[str, Any]]]:
    """File name -> the resources it holds."""
    files: dict[str, list[dict[str, Any]]] = {"router.yaml": router(), "storage.yaml": claims()}
    for task in TASKS:
        files[f"{task.replace('_', '-')}.yaml"] = [model_service(r, task) for r in SERVICE_ROLES]
    files["gateway.yaml"] = [gateway(), _service("gateway", GATEWAY_PORT, "http")]
    return files


def write(out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    yaml = YAML()
    yaml.default_flow_style = False
    yaml.representer.ignore_aliases = lambda *_: True  # plain YAML: every resource spelled out
    written = []
    for name, resources in manifests().items():
        path = out / name
        with path.open("w") as f:
            f.write("# Written by `python -m shared.k8s --out deploy/k8s`: edit that, not this.\n")
            yaml.dump_all(resources, f)
        written.append(path)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("deploy/k8s"))
    for path in write(parser.parse_args().out):
        print(path)


if __name__ == "__main__":
    main()

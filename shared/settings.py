"""Settings every process reads from the environment (LSR_*); command-line flags override them."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from shared.bus import DEFAULT_ENDPOINT, BusConfig
from shared.tasks import DEFAULT_TASK

# The shipped models, found from the source tree (not the working directory): one folder a task.
MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
SHIPPED_MODEL = MODELS_DIR / DEFAULT_TASK
MODEL_PARTS = ("vae", "roadmap", "apn")  # what the services load


def shipped_models() -> tuple[Path, ...]:
    """Every shipped model folder with all the parts the services load."""
    folders = MODELS_DIR.iterdir() if MODELS_DIR.is_dir() else ()
    return tuple(sorted(p for p in folders if all((p / part).is_dir() for part in MODEL_PARTS)))


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="LSR_")

    zenoh_connect: str = Field(DEFAULT_ENDPOINT, description="router endpoints, comma-separated")
    zenoh_open_timeout_s: float | None = Field(
        None, description="give up joining after this long; unset: retry until a router is up"
    )
    zenoh_config: Path | None = Field(
        None, description="zenoh configuration file: credentials, TLS; the router's: access control"
    )
    model_dir: Path = SHIPPED_MODEL
    require_sealed_model: bool = Field(
        False, description="refuse model parts without a MANIFEST.json (deployments)"
    )
    instance: str | None = Field(None, description="instance id; default hostname-pid-random")
    torch_threads: int = Field(1, ge=1)
    tasks: list[str] = Field(
        [DEFAULT_TASK], description="gateway: the tasks served (JSON list); others get 404"
    )
    task_specs: dict[str, dict] = Field(
        {},
        description="gateway: the specs of served tasks defined by their data (JSON object by "
        "task); they have no simulator",
    )
    deadline_s: float = Field(
        4.0, gt=0, description="per request: all its service calls, retries included"
    )
    execute_step_s: float = Field(3.0, gt=0, description="/execute allowance per step")
    max_body_bytes: int = Field(4 * 1024 * 1024, gt=0)
    body_timeout_s: float = Field(
        10.0, gt=0, description="a request body must arrive within this (408 after)"
    )
    max_in_flight: int = Field(32, ge=1, description="/plan and /render requests in progress")
    max_executing: int = Field(4, ge=1, description="/execute requests in progress")
    light_body_bytes: int = Field(
        192 * 1024,
        ge=0,
        description="bodies up to this are light (states, views); larger ones bring camera "
        "frames and share LSR_MAX_FRAMES_IN_FLIGHT",
    )
    max_frames_in_flight: int = Field(
        4, ge=1, description="requests with camera frames in progress (the rest: 503)"
    )
    max_frames_queued: int = Field(8, ge=0, description="requests with frames waiting for a slot")
    max_queued: int = Field(256, ge=0, description="requests waiting for a slot; more: 503")
    queue_wait_s: float = Field(2.0, ge=0, description="longest wait for a slot; then 503")
    api_key_hashes: str = Field(
        "", description="sha256 digests of accepted REST API keys, comma-separated; '': off"
    )
    api_keys_file: Path | None = Field(
        None, description="a file of sha256 digests of accepted REST API keys, one a line"
    )
    require_api_keys: bool = Field(
        False, description="refuse to start the gateway without API key digests (deployments)"
    )
    experience_dir: Path | None = Field(
        None,
        description="gateway: where robots' reported experience is recorded, a folder per task "
        "(for lsr roadmap grow); unset: reports are answered 503",
    )
    host: str = "127.0.0.1"
    port: int = 8000

    def bus(self) -> BusConfig:
        endpoints = [e.strip() for e in self.zenoh_connect.split(",") if e.strip()]
        return BusConfig(
            connect=endpoints,
            open_timeout_s=self.zenoh_open_timeout_s,
            config_file=self.zenoh_config,
        )

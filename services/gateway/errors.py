"""The HTTP status and `detail` of every error the gateway expects.

Shared by the API routes (`app.py`), the public zenoh queries (`queries.py`) and the plan
viewer's event stream (`viewer.py`), so that none of them imports another to answer alike.
"""

from __future__ import annotations

from typing import Any

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.data.experience import ExperienceError
from services.gateway.inputs import BodyError, clip, error_detail
from services.gateway.planning import TaskNotServed
from shared.bus import RemoteError, ServiceUnavailable
from shared.validation import FieldError


def error_body(exc: Exception) -> tuple[int, Any] | None:
    """The HTTP status and `detail` for the errors the gateway expects; None for a bug.

    Details name the field and echo at most a short excerpt of the input (`inputs.error_detail`).
    """
    if isinstance(exc, BodyError):
        return exc.status, exc.detail()
    if isinstance(exc, FieldError):
        loc = ["body", *exc.field.split(".")]
        return 422, error_detail([{"loc": loc, "msg": str(exc), "type": "value_error"}])
    if isinstance(exc, ValidationError):
        return 422, error_detail(exc.errors(include_url=False), prefix=["body"])
    if isinstance(exc, RequestValidationError):  # FastAPI's: locations start with "body"
        return 422, error_detail(exc.errors())
    if isinstance(exc, TaskNotServed):
        return 404, clip(str(exc))
    if isinstance(exc, ExperienceError):  # the folder holds another model's experience
        return 409, clip(str(exc))
    if isinstance(exc, ServiceUnavailable):
        return 503, clip(str(exc))
    if isinstance(exc, RemoteError):
        return (422 if exc.error.code == "bad_request" else 502), clip(str(exc))
    return None

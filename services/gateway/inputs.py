"""Untrusted input: JSON bodies parsed within limits, and error details that are safe to echo.

FastAPI's own path (any body through `json.loads`, then pydantic, then every error with its
whole input echoed back) costs time and memory in proportion to what a caller sends, and ends
in a 500 on values that cannot go back out as JSON: NaN, lone surrogates, raw bytes. REST bodies
and `lsr/api/plan` payloads both go through `parse_json` first, and every error detail through
`error_detail`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

# A plan request holds about 30 JSON values; far more is work nobody legitimately asks for.
MAX_JSON_ITEMS = 1000  # object members and array items, all levels together
MAX_JSON_DEPTH = 32
MAX_ERRORS = 10  # errors listed in one reply
EXCERPT_CHARS = 80  # of any input or message echoed back
MESSAGE_CHARS = 300


class BodyError(ValueError):
    """A body refused before validation; `loc` and `kind` as in pydantic's errors."""

    def __init__(self, status: int, loc: Sequence[str | int], message: str, kind: str) -> None:
        super().__init__(message)
        self.status = status
        self.loc = list(loc)
        self.kind = kind

    def detail(self) -> list[dict[str, Any]]:
        return error_detail([{"loc": self.loc, "msg": str(self), "type": self.kind}])


def parse_json(body: bytes) -> Any:
    """A request body as JSON, refusing before any costly step what no request needs.

    NaN, Infinity and numbers beyond float range stay (as floats): the schema refuses them
    where it must, naming the field. Lone surrogate escapes stay too, for the same reason.
    """
    # Every comma separates two items; counting them is a quick upper bound found before the
    # parser builds hundreds of thousands of objects. (Commas inside strings count too: no
    # field of a valid request has more than a few.)
    commas = body.count(b",")
    if commas >= MAX_JSON_ITEMS:
        raise BodyError(
            422,
            ["body"],
            f"{commas} commas: JSON bodies may hold at most {MAX_JSON_ITEMS} items",
            "too_many_items",
        )
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BodyError(
            422, ["body", exc.start], f"not UTF-8 at byte {exc.start}", "json_invalid"
        ) from None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BodyError(
            422, ["body", exc.pos], f"JSON decode error: {exc.msg}", "json_invalid"
        ) from None
    except RecursionError:
        raise BodyError(422, ["body"], "JSON nested too deeply", "json_invalid") from None
    except ValueError as exc:  # an integer of more than 4300 digits
        raise BodyError(422, ["body"], clip(str(exc)), "json_invalid") from None
    check_size(value)
    return value


def check_size(value: Any) -> None:
    """At most MAX_JSON_ITEMS items, at most MAX_JSON_DEPTH levels (stops at the first excess)."""
    items = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict):
            children: Iterable[Any] = node.values()
        elif isinstance(node, list):
            children = node
        else:
            continue
        if depth >= MAX_JSON_DEPTH:
            raise BodyError(
                422, ["body"], f"JSON nested deeper than {MAX_JSON_DEPTH} levels", "too_deep"
            )
        items += len(node)
        if items > MAX_JSON_ITEMS:
            raise BodyError(
                422,
                ["body"],
                f"JSON bodies may hold at most {MAX_JSON_ITEMS} items",
                "too_many_items",
            )
        stack.extend((child, depth + 1) for child in children)


def clip(text: str, limit: int = MESSAGE_CHARS) -> str:
    """At most `limit` characters, lone surrogates written as escapes: always encodable."""
    if len(text) > limit:
        text = text[:limit] + "..."
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def excerpt(value: Any, budget: int = EXCERPT_CHARS) -> Any:
    """A JSON-safe stand-in for an input: scalars as they are, the rest as short text."""
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int):
        return value if abs(value) < 2**63 else clip(str(value), budget)
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if isinstance(value, str):
        return clip(value, budget)
    if isinstance(value, bytes | bytearray):
        return f"<{len(value)} bytes>"
    return clip(_preview(value, budget), budget)


def _preview(value: Any, budget: int) -> str:
    """JSON-like text of a container, cut off after about `budget` characters."""
    parts: list[str] = []
    used = 0

    def add(text: str) -> bool:
        nonlocal used
        parts.append(text)
        used += len(text)
        return used < budget

    def walk(node: Any) -> bool:
        if isinstance(node, dict):
            if not add("{"):
                return False
            for i, (key, child) in enumerate(node.items()):
                if not add((", " if i else "") + json.dumps(clip(str(key), budget)) + ": "):
                    return False
                if not walk(child):
                    return False
            return add("}")
        if isinstance(node, list | tuple):
            if not add("["):
                return False
            for i, child in enumerate(node):
                if (i and not add(", ")) or not walk(child):
                    return False
            return add("]")
        return add(json.dumps(excerpt(node, budget)))

    walk(value)
    return "".join(parts)


def error_detail(
    errors: Sequence[Mapping[str, Any]], prefix: Sequence[str] = ()
) -> list[dict[str, Any]]:
    """pydantic-style errors made safe to send: at most MAX_ERRORS, each naming its field,
    with a short excerpt of the input instead of the input itself."""
    detail = []
    for error in errors[:MAX_ERRORS]:
        item: dict[str, Any] = {
            "loc": [
                *prefix,
                *(p if isinstance(p, int) else clip(str(p), 64) for p in error["loc"]),
            ],
            "msg": clip(str(error.get("msg", ""))),
            "type": clip(str(error.get("type", "value_error")), 64),
        }
        if "input" in error:
            item["input"] = excerpt(error["input"])
        ctx = error.get("ctx")
        if isinstance(ctx, Mapping):  # limits such as {"ge": 1}; exceptions repeat `msg`
            kept = {clip(str(k), 64): excerpt(v) for k, v in ctx.items() if _scalar(v)}
            if kept:
                item["ctx"] = kept
        detail.append(item)
    if len(errors) > MAX_ERRORS:
        more = len(errors) - MAX_ERRORS
        detail.append({"loc": list(prefix), "msg": f"and {more} more errors", "type": "more"})
    return detail


def _scalar(value: Any) -> bool:
    return value is None or isinstance(value, bool | int | float | str)

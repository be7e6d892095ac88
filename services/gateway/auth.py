"""REST API keys (opt-in): `Authorization: Bearer KEY`, checked against sha256 digests.

The gateway stores no key, only digests (from LSR_API_KEY_HASHES and/or LSR_API_KEYS_FILE), so a
leaked configuration reveals none. Keys are random tokens of 256 bits: a plain sha256 needs no
slow hash. Nothing here logs or echoes a key, nor a line of the keys file (a key pasted there by
mistake would otherwise end up in a log).

    python -m services.gateway.auth new   # prints a new key, then the digest line to configure
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import sys
from collections.abc import Iterable
from pathlib import Path

from starlette.types import ASGIApp, Receive, Scope, Send

from services.gateway.middleware import send_json

DIGEST = re.compile(r"^(?:sha256:)?([0-9a-f]{64})$")
OPEN_PATHS = frozenset({"/health"})  # for load balancers and `lsr ping`-like checks
# The plan viewer's static files hold no data; the page sends the user's key with every call.
OPEN_PAGES = ("/", "/ui/")


def digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def parse_digests(lines: Iterable[str], where: str) -> frozenset[bytes]:
    """Digests from `lines`: `[sha256:]HEX [label]`, blank lines and `#` comments skipped."""
    found = set()
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        match = DIGEST.match(text.split()[0].lower())
        if match is None:  # the line itself is not shown: it may be a key pasted by mistake
            raise ValueError(f"{where}, entry {number}: not a sha256 digest (64 hex digits)")
        found.add(bytes.fromhex(match.group(1)))
    return frozenset(found)


def load_digests(hashes: str, keys_file: Path | None) -> frozenset[bytes]:
    """The accepted key digests from the settings; empty: API keys are off."""
    found = parse_digests(hashes.split(","), "LSR_API_KEY_HASHES")
    if keys_file is not None:
        found |= parse_digests(keys_file.read_text().splitlines(), str(keys_file))
    return found


def is_open(path: str) -> bool:
    return path in OPEN_PATHS or path == OPEN_PAGES[0] or path.startswith(OPEN_PAGES[1])


class ApiKeys:
    """401 for every request but OPEN_PATHS without a known bearer key."""

    def __init__(self, app: ASGIApp, digests: frozenset[bytes]) -> None:
        self.app = app
        self.digests = digests

    def accepts(self, authorization: bytes | None) -> bool:
        scheme, _, key = (authorization or b"").partition(b" ")
        if scheme.lower() != b"bearer" or not key.strip():
            return False
        presented = hashlib.sha256(key.strip()).digest()
        # Compared with every digest, in constant time each: no timing tells which one is near.
        matches = [hmac.compare_digest(presented, known) for known in self.digests]
        return any(matches)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or is_open(scope["path"]):
            return await self.app(scope, receive, send)
        if self.accepts(dict(scope["headers"]).get(b"authorization")):
            return await self.app(scope, receive, send)
        detail = "a valid API key is required: Authorization: Bearer KEY"
        await send_json(send, 401, detail, [(b"www-authenticate", b'Bearer realm="lsr"')])


def main(argv: list[str]) -> int:
    if argv != ["new"]:
        print("usage: python -m services.gateway.auth new", file=sys.stderr)
        return 2
    key = secrets.token_urlsafe(32)
    print(f"key (give it to the client; it is not stored): {key}")
    print(f"digest line (LSR_API_KEY_HASHES or LSR_API_KEYS_FILE): sha256:{digest(key)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

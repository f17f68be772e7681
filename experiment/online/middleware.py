"""The server's ASGI middleware: cross-origin POSTs refused, request bodies over
:data:`MAX_BODY_BYTES` refused before parsing (declared or chunked), JSON bodies that spell
text no Unicode string holds (a lone UTF-16 surrogate) refused, and the security headers
(a strict Content-Security-Policy, ``nosniff``, ``no-referrer``, no framing) on every response.
"""

from __future__ import annotations

import base64
import hashlib
import json
from typing import Any

from fastapi import FastAPI
from fastapi.responses import JSONResponse

__all__ = ["CSP", "IMPORT_MAP", "MAX_BODY_BYTES", "SecurityHeaders"]

#: the session page's import map (the live 3D/VR view imports three.js by its bare name); an
#: inline script, so the policy allows exactly these bytes by their hash
IMPORT_MAP = (
    '{"imports": {"three": "/vendor/three/build/three.module.js", '
    '"three/addons/": "/vendor/three/examples/jsm/"}}'
)
_IMPORT_MAP_HASH = base64.b64encode(hashlib.sha256(IMPORT_MAP.encode()).digest()).decode()
CSP = (
    f"default-src 'none'; script-src 'self' 'sha256-{_IMPORT_MAP_HASH}'; "
    "style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; media-src 'self' blob:; connect-src 'self' blob:; "
    "font-src 'self' data:; "
    "base-uri 'none'; "
    "form-action 'self'; frame-ancestors 'none'"
)


_HEADERS = [
    (b"content-security-policy", CSP.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
    (b"cross-origin-opener-policy", b"same-origin"),
]


#: the largest request body accepted (a playback record of a 30 s clip is ~20 KB; the field
#: limits allow ~2 MB): anything larger is refused with 413 before it is parsed
MAX_BODY_BYTES = 4 * 2**20


class SecurityHeaders:
    """Pure ASGI middleware: cross-origin POSTs refused, request bodies over
    :data:`MAX_BODY_BYTES` refused (by Content-Length, or counted as a chunked body arrives),
    security headers on every response (cheaper than Starlette's BaseHTTPMiddleware under
    load)."""

    def __init__(self, app: FastAPI):
        self.app = app
        self.state = app.state

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        origin = headers.get(b"origin")
        cross = origin is not None and origin.split(b"://", 1)[-1] != headers.get(b"host", b"")
        if scope["method"] == "POST" and cross:
            refusal = JSONResponse({"error": "cross-origin request refused"}, status_code=403)
            await refusal(scope, receive, send)
            return
        api = scope["path"].startswith("/api/")

        async def send_with_headers(message: Any) -> None:
            if message["type"] == "http.response.start":
                extra = _HEADERS + ([(b"cache-control", b"no-store")] if api else [])
                message["headers"] = list(message.get("headers", [])) + extra
            await send(message)

        body = b""
        declared = headers.get(b"content-length", b"0")
        too_large = not declared.isdigit() or int(declared) > MAX_BODY_BYTES
        if not too_large and scope["method"] in ("POST", "PUT", "PATCH"):
            body = await _read_body(receive)
            too_large = body is None
            receive = receive if body is None else _replay(body, receive)
        if too_large:
            refusal = JSONResponse(
                {"error": f"request body larger than {MAX_BODY_BYTES} bytes"}, status_code=413
            )
            await refusal(scope, receive, send_with_headers)
            return
        bad = _lone_surrogate(body) if scope["method"] == "POST" and api else None
        if bad is not None:
            refusal = JSONResponse(
                {"error": f"{bad} that is not UTF-8 Unicode (a lone UTF-16 surrogate, "
                 "\\ud800-\\udfff not in a pair, or another encoding)"}, status_code=422,
            )  # fmt: skip
            await refusal(scope, receive, send_with_headers)
            return
        await self.app(scope, receive, send_with_headers)


def _not_text(value: str) -> bool:
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _lone_surrogate(body: bytes | None) -> str | None:
    """Where a JSON body holds a surrogate that is not half of a pair (``"\\ud800"``) -
    ``field.sub: a key`` / ``field.sub: text`` (``body`` at the top; ``body: text`` for a body
    that is not strict UTF-8 - raw surrogate bytes, or UTF-16/32, which Python's JSON reader
    would accept) - or None. Python parses such a surrogate into a str that cannot be
    encoded, stored or answered (the validator and the database raise on it). A pair (an
    emoji spelled as escapes) is text and passes; a body that is not JSON is left for the
    route to refuse."""
    if not body:
        return None
    try:
        body.decode("utf-8")  # strict: encoded surrogates (ED A0 80 ...) are refused
    except UnicodeDecodeError:
        return "body: text"
    if b"\x00" in body:  # JSON never holds a raw NUL: this is UTF-16 or UTF-32
        return "body: text"
    if b"\\u" not in body:
        return None
    try:
        parsed = json.loads(body)
    except (ValueError, RecursionError):
        return None
    stack: list[tuple[tuple[str, ...], Any]] = [((), parsed)]
    while stack:  # depth first, in the body's order
        path, value = stack.pop()
        where = ".".join(path) or "body"
        if isinstance(value, str) and _not_text(value):
            return f"{where}: text"
        if isinstance(value, dict):
            if any(_not_text(k) for k in value):
                return f"{where}: a key"
            stack += [((*path, k), v) for k, v in reversed(value.items())]
        elif isinstance(value, list):
            stack += [((*path, str(i)), v) for i, v in reversed(list(enumerate(value)))]
    return None


async def _read_body(receive: Any) -> bytes | None:
    """A request's whole body (chunked or not), or None once it passes MAX_BODY_BYTES."""
    body = bytearray()
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return bytes(body)  # the client went away; the app will see it
        body += message.get("body", b"")
        if len(body) > MAX_BODY_BYTES:
            return None
        if not message.get("more_body", False):
            return bytes(body)


def _replay(body: bytes, receive: Any) -> Any:
    """An ASGI receive that gives ``body`` first, then whatever the client sends next."""
    sent = False

    async def replay() -> Any:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay

"""Authentication of HTTP requests and websockets, as ASGI middleware.

Once a token is configured (setting ``token``, or ``ESIAF_TOKEN`` / ``ESIAF_TOKEN_FILE``), every
request but ``GET /health`` and the dashboard's files (``GET /``, ``/dashboard/...``, which hold no
data) must carry it as ``Authorization: Bearer TOKEN`` or, for browsers, ``?token=TOKEN``; a missing
or wrong one gets 401. A websocket must carry it too, and a browser's websocket (one with an
``Origin`` header) must come from the orchestrator's own origin or one in ``allowed_origins``, so a
page elsewhere cannot read the results through the user's browser.
Refused websockets are closed before the handshake completes (the client sees HTTP 403).
"""
from __future__ import annotations

import hmac
import json
import logging
from collections.abc import Awaitable, Callable
from typing import Any
from urllib.parse import parse_qs

log = logging.getLogger(__name__)

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]
OPEN_PATHS = {"/health", "/"}  # "/": the dashboard's page, which holds no data (it reads the API with the token)
OPEN_PREFIXES = ("/dashboard/",)  # the dashboard's scripts and styles


def is_open(method: str | None, path: str) -> bool:
    """Whether a request needs no token."""
    return method in ("GET", "HEAD") and (path in OPEN_PATHS or path.startswith(OPEN_PREFIXES))


def _open(scope: Scope) -> bool:
    return is_open(scope.get("method"), scope["path"])


class TokenAuth:
    def __init__(self, app: Callable[[Scope, Receive, Send], Awaitable[None]], token: str,
                 allowed_origins: list[str]) -> None:
        self.app = app
        self.token = token.encode()
        self.allowed_origins = {origin.rstrip("/") for origin in allowed_origins}
        self.refused = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or (scope["type"] == "http" and _open(scope)):
            await self.app(scope, receive, send)
            return
        problem = self._problem(scope)
        if problem is None:
            await self.app(scope, receive, send)
            return
        self.refused += 1
        if self.refused == 1 or self.refused % 100 == 0:
            log.warning("event=refused path=%s reason=%r count=%d", scope["path"], problem, self.refused)
        if scope["type"] == "websocket":
            await receive()  # websocket.connect
            await send({"type": "websocket.close", "code": 1008, "reason": problem})
            return
        body = json.dumps({"detail": problem}).encode()
        await send({"type": "http.response.start", "status": 401,
                    "headers": [(b"content-type", b"application/json"), (b"www-authenticate", b"Bearer"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})

    def _problem(self, scope: Scope) -> str | None:
        headers = dict(scope.get("headers") or [])
        if self.token:
            given = b""
            authorization = headers.get(b"authorization", b"")
            if authorization[:7].lower() == b"bearer ":
                given = authorization[7:].strip()
            else:
                query = parse_qs(scope.get("query_string", b"").decode(errors="replace"))
                given = query.get("token", [""])[0].encode()
            if not given:
                return "a token is required: Authorization: Bearer TOKEN, or ?token=TOKEN"
            if not hmac.compare_digest(given, self.token):
                return "wrong token"
        if scope["type"] == "websocket" and b"origin" in headers:
            origin = headers[b"origin"].decode(errors="replace").rstrip("/")
            host = headers.get(b"host", b"").decode(errors="replace")
            if origin not in self.allowed_origins and origin not in (f"http://{host}", f"https://{host}"):
                return f"websocket origin {origin} is not allowed (setting allowed_origins)"
        return None

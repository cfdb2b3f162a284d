"""The launcher's view of the fused results: a websocket that survives an orchestrator restart."""
from __future__ import annotations

import json
import logging
import sys
import time
from contextlib import ExitStack

from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import ClientConnection, connect

from esiaf import auth

log = logging.getLogger(__name__)


class FusedFeed:
    """The websocket of fused results. If the orchestrator goes away (it died and is being
    restarted), it reconnects with ``after_seq`` = the last publication seen, so no fused
    result or revision is missed; meanwhile ``recv`` times out as if nothing had arrived."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.last_seq: int | None = None
        self.ssl = auth.tls_context() if url.startswith("wss:") else None  # ws://: none
        self.ws: ClientConnection | None = None
        self._open = ExitStack()  # the connection, entered as websockets asks (a bare connect() is deprecated)
        self._connect(url, 10.0)

    def _connect(self, url: str, timeout: float) -> ClientConnection:
        self.ws = self._open.enter_context(connect(url, open_timeout=timeout, additional_headers=auth.headers(),
                                                   ssl=self.ssl))
        return self.ws

    def __enter__(self) -> FusedFeed:
        return self

    def __exit__(self, *exc) -> None:
        self._open.close()
        self.ws = None

    def recv(self, timeout: float) -> str | bytes:
        ws = self.ws
        if ws is None:
            after = f"after_seq={self.last_seq}" if self.last_seq is not None else ""
            url = self.url + ("&" if "?" in self.url else "?") + after if after else self.url
            try:
                ws = self._connect(url, timeout)
            except (OSError, TimeoutError, WebSocketException) as exc:  # not back yet, or going away again
                log.debug("websocket not reconnected: %s: %s", type(exc).__name__, exc)
                time.sleep(timeout)
                raise TimeoutError from None
            log.info("websocket reconnected after_seq=%s", self.last_seq)
        try:
            text = ws.recv(timeout=timeout)
        except ConnectionClosed:
            self._open.close()
            self.ws = None
            print("esiaf: lost the orchestrator's websocket; reconnecting", file=sys.stderr, flush=True)
            raise TimeoutError from None
        try:  # what the message is, is the caller's to judge; here only its publication number counts
            seq = json.loads(text).get("seq")
        except (ValueError, AttributeError):
            seq = None
        if isinstance(seq, int):
            self.last_seq = seq
        return text

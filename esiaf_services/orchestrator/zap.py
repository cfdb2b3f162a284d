"""Who may connect to the orchestrator's control and results sockets (ZAP), and who was refused.

- CURVE keys (``ESIAF_CURVE_DIR``, esiaf/keys.py): the sockets are CURVE servers with the
  orchestrator's key pair, and take only the client keys in ``DIR/clients/`` (read at start-up and
  again on SIGHUP: a new robot's key is let in, a withdrawn one kept out, without a restart).
- else a token: PLAIN, user ``esiaf``, password the token. It travels in clear text: loopback or a
  network no one else is on (an encrypted overlay) only.
- neither: anyone (NULL).

Every refused handshake is counted per socket and reason (``keys.HANDSHAKE_FAILURES``: ``auth``, a
key or token not allowed; ``protocol``, another mechanism, e.g. no keys; ``other``, ended
mid-handshake) and logged, the first and every 100th: a socket monitor sees them, whichever side
gave up. ``GET /metrics`` shows them as ``esiaf_refused_peers``.
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Coroutine
from typing import Any

import zmq.asyncio
from zmq.auth.asyncio import AsyncioAuthenticator
from zmq.utils.monitor import parse_monitor_message

from esiaf import auth, keys

log = logging.getLogger(__name__)


class Guard:
    def __init__(self, context: zmq.asyncio.Context, token: str, curve: keys.Curve | None) -> None:
        self.context = context
        self.token = token
        self.curve = curve
        self.refused: Counter[tuple[str, str]] = Counter()  # (socket, reason) -> handshakes refused
        self._authenticator: AsyncioAuthenticator | None = None
        self._monitors: list[tuple[str, zmq.asyncio.Socket]] = []

    @property
    def mechanism(self) -> str:
        return "curve" if self.curve else "plain" if self.token else "null"

    def start(self) -> None:
        if self.mechanism == "null":
            return
        self._authenticator = AsyncioAuthenticator(self.context)
        self._authenticator.start()
        if self.curve is not None:
            self._authenticator.configure_curve(domain="*", location=str(self.curve.clients_dir))
        else:
            self._authenticator.configure_plain(domain="*", passwords={auth.ZMQ_USER: self.token})

    def reload(self) -> int | None:
        """Reads the allowed client keys again (SIGHUP; keys.reload_clients); their number, or None
        without CURVE keys or if a key file cannot be read (logged, never fatal: the old set stays)."""
        allowed = keys.reload_clients(self.curve if self._authenticator is not None else None, self._authenticator)
        return None if allowed is None else len(allowed)

    def secure(self, socket: zmq.asyncio.Socket, name: str) -> None:
        """Before bind: makes ``socket`` a PLAIN or CURVE server and counts its refused peers."""
        if self.mechanism == "null":
            return
        if self.curve is not None:
            keys.server(socket, self.curve)
        else:
            socket.plain_server = True
        self._monitors.append((name, socket.get_monitor_socket(sum(keys.HANDSHAKE_FAILURES))))

    def watchers(self) -> list[Coroutine[Any, Any, None]]:
        """What the orchestrator runs as tasks: one loop per secured socket, counting refusals."""
        return [self._watch(monitor, name) for name, monitor in self._monitors]

    async def _watch(self, monitor: zmq.asyncio.Socket, name: str) -> None:
        try:
            while True:
                event = parse_monitor_message(await monitor.recv_multipart())
                reason = keys.HANDSHAKE_FAILURES.get(event["event"], "other")
                self.refused[name, reason] += 1
                count = self.refused[name, reason]
                if count == 1 or count % 100 == 0:
                    log.warning("event=peer_refused socket=%s mechanism=%s reason=%s count=%d",
                                name, self.mechanism, reason, count)
        finally:
            monitor.close(linger=0)

    def stop(self) -> None:
        """After the watchers' tasks have ended."""
        if self._authenticator is not None:
            self._authenticator.stop()
            self._authenticator = None

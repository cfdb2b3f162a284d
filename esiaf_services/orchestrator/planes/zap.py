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
gave up. ``GET /metrics`` shows them as ``esiaf_refused_peers``. The same monitor (libzmq allows
one per socket) reports closed connections to whoever asks (the control plane).
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Coroutine
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
        self._monitors: list[tuple[str, zmq.asyncio.Socket, Callable[[int], object] | None]] = []

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

    def secure(self, socket: zmq.asyncio.Socket, name: str,
               on_disconnect: Callable[[int], object] | None = None) -> None:
        """Before bind: makes ``socket`` a PLAIN or CURVE server and counts its refused peers; tells
        ``on_disconnect`` the file descriptor of every connection of it that closes."""
        events = zmq.EVENT_DISCONNECTED if on_disconnect is not None else 0
        if self.mechanism != "null":
            if self.curve is not None:
                keys.server(socket, self.curve)
            else:
                socket.plain_server = True
            events |= sum(keys.HANDSHAKE_FAILURES)
        if events:
            self._monitors.append((name, socket.get_monitor_socket(events), on_disconnect))

    def watchers(self) -> list[Coroutine[Any, Any, None]]:
        """What the orchestrator runs as tasks: one loop per monitored socket."""
        return [self._watch(monitor, name, on_disconnect) for name, monitor, on_disconnect in self._monitors]

    async def _watch(self, monitor: zmq.asyncio.Socket, name: str,
                     on_disconnect: Callable[[int], object] | None) -> None:
        try:
            while True:
                event = parse_monitor_message(await monitor.recv_multipart())
                if event["event"] == zmq.EVENT_DISCONNECTED:
                    if on_disconnect is not None:
                        on_disconnect(int(event["value"]))
                    continue
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

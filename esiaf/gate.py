"""Who may subscribe to a producer's audio without CURVE keys: the consumers the orchestrator names.

A producer's audio socket (its XPUB) is a PLAIN server; a consumer's SUB presents its component id as
the PLAIN user name and the token as the password (no password without a token: esiaf/auth.py). The
:class:`ConsumerGate` is the producer's ZAP handler (a thread, on the socket's context): it takes a
subscriber only if it presents the token and its name is one of the consumers of the producer's outputs
that the orchestrator named in its state (``consumers``; a host's guests' consumers too). A name not
named yet is held up to HOLD_S, as a consumer that has just registered may connect before the producer
has applied the state that names it; then refused. So a peer without the token, or one the orchestrator
never registered, never gets a queue at the producer: live audio is never dropped for it and a replay
never waits for it (docs/protocol.md, "Flow control"). With CURVE keys the allowed client keys decide
instead (esiaf/keys.py). Refused handshakes are counted by the producer's socket monitor
(``refused_subscribers`` in its heartbeat) and logged here with their reason, the first and every 100th.
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Iterable

import zmq

log = logging.getLogger(__name__)

ZAP_ENDPOINT = "inproc://zeromq.zap.01"  # where libzmq asks a context's ZAP handler (RFC 27)
HOLD_S = 5.0  # a subscriber whose name is not (yet) among the consumers named waits this long for it
MAX_HELD = 64  # subscribers held at once; more are refused at once
MAX_NAME = 200  # characters of a component id


class ConsumerGate:
    """The ZAP handler of one producer's audio socket (see the module). Bind it before the socket."""

    def __init__(self, context: zmq.Context, token: str) -> None:
        self._token = token
        self._named: dict[str, frozenset[str] | None] = {}  # by the registration that named them
        self._allowed: frozenset[str] | None = frozenset()  # None: any name (the orchestrator names none)
        self._naming = threading.Lock()
        self.refused: Counter[str] = Counter()  # by reason, for the log
        self._closing = False
        self._handler = context.socket(zmq.ROUTER)  # a ROUTER, not a REP: a held request must not block others
        self._handler.setsockopt(zmq.LINGER, 0)
        self._handler.bind(ZAP_ENDPOINT)
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_read, False)
        os.set_blocking(self._wake_write, False)
        self._thread = threading.Thread(target=self._run, name="esiaf-audio-gate", daemon=True)
        self._thread.start()

    def name(self, source: str, consumers: Iterable[str] | None) -> None:
        """The consumers the orchestrator names in ``source``'s state (the producer's registration, or a
        guest's that publishes through its socket); None if it names none (an orchestrator that does not
        know them): then any subscriber with the token is taken. Safe from any thread."""
        with self._naming:  # the node's data thread and a guest's state thread
            self._named[source] = None if consumers is None else frozenset(
                c for c in consumers if isinstance(c, str) and len(c) <= MAX_NAME)
            lists = [v for v in self._named.values() if v is not None]
            self._allowed = None if len(lists) < len(self._named) else frozenset().union(*lists)
        self._wake()

    def close(self) -> None:
        self._closing = True
        self._wake()
        self._thread.join(timeout=2.0)
        for fd in (self._wake_read, self._wake_write):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # full: woken already
            os.write(self._wake_write, b"!")

    def _run(self) -> None:
        poller = zmq.Poller()
        poller.register(self._handler, zmq.POLLIN)
        poller.register(self._wake_read, zmq.POLLIN)
        held: list[tuple[float, list[bytes]]] = []  # (deadline, request), oldest first
        try:
            while not self._closing:
                timeout = max(1, round(1000 * (held[0][0] - time.monotonic()))) if held else None
                ready = dict(poller.poll(timeout))
                if self._wake_read in ready:
                    with contextlib.suppress(OSError):
                        os.read(self._wake_read, 4096)
                now = time.monotonic()
                with contextlib.suppress(zmq.Again):
                    while True:
                        held.append((now + HOLD_S, self._handler.recv_multipart(zmq.NOBLOCK)))
                waiting: list[tuple[float, list[bytes]]] = []
                for deadline, request in held:
                    why = self._verdict(request)
                    if why is None and now < deadline and len(waiting) < MAX_HELD:
                        waiting.append((deadline, request))
                    else:
                        self._reply(request, why if why is not None else
                                    "not a consumer the orchestrator named" if now >= deadline else "too many held")
                held = waiting
        finally:
            self._handler.close(linger=0)

    def _verdict(self, request: list[bytes]) -> str | None:
        """"" to take the subscriber, the reason to refuse it, or None to hold it (not named yet)."""
        # [routing id, b"", version, request id, domain, address, identity, mechanism, credentials...]
        if len(request) < 8 or request[1] != b"" or request[2] != b"1.0":
            return "not a ZAP request"
        mechanism, credentials = request[7], request[8:]
        if mechanism != b"PLAIN" or len(credentials) != 2:
            return f"mechanism {mechanism[:16]!r}"
        user, password = credentials
        if password.decode("utf-8", "replace") != self._token:
            return "no token" if not password else "wrong token"
        allowed = self._allowed
        if allowed is None or user.decode("utf-8", "replace") in allowed:
            return ""
        return None

    def _reply(self, request: list[bytes], why: str) -> None:
        if len(request) < 4:
            return
        user = request[8] if not why and len(request) > 8 else b""
        if why:
            self.refused[why] += 1
            if self.refused[why] == 1 or self.refused[why] % 100 == 0:
                name = request[8][:MAX_NAME] if len(request) > 8 else b""
                log.warning("refused a subscriber reason=%s name=%.200r count=%d", why, name, self.refused[why])
        with contextlib.suppress(zmq.ZMQError):  # the connection may be gone
            self._handler.send_multipart([request[0], b"", b"1.0", request[3], b"400" if why else b"200",
                                          why.encode(), user, b""])

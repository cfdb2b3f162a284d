"""Bounds on the HTTP layer, below the app: what a peer can hold before it has sent a request.

uvicorn times out only the idle time between two requests on a connection: a request whose
headers never end holds its connection, and a file descriptor, for ever. Here, on uvicorn's h11
protocol:

- a request must have arrived whole (headers and body) within ``request_timeout_s`` of its
  first byte (of the connection's opening, for the first request), or its connection is closed
  (408 while its headers are incomplete);
- a peer (an IP address) holds at most ``max_connections_per_peer`` connections, and all peers
  together at most what the file limit leaves after a reserve for the database, the ZeroMQ sockets
  and their connections: a connection over either bound is closed as it is accepted;
- the file limit is raised to its hard limit at start-up (:func:`raise_file_limit`);
- the event loop backs off for a second after an accept that failed for want of a file descriptor,
  and logs it once per ``LOG_EVERY_S`` with the count since (Python's asyncio before gh-151615 went
  on trying, scheduling a retry and logging a traceback for each attempt).

Every connection closed so is counted per reason (``refused``: the orchestrator's ``http_refused``,
``esiaf_refused_http_connections`` in ``GET /metrics``) and logged, the first of a reason and then at
most once per ``LOG_EVERY_S``.
"""
from __future__ import annotations

import asyncio
import errno
import logging
import resource
import time
from collections import Counter
from typing import Any, ClassVar

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

LOG_EVERY_S = 10.0
RESOURCE_ERRORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
TIMEOUT_BODY = b"request not sent in time\n"
TIMEOUT_RESPONSE = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
                    b"content-length: %d\r\n\r\n%s" % (len(TIMEOUT_BODY), TIMEOUT_BODY))


def raise_file_limit() -> int:
    """Raises this process's limit of open files to its hard limit; returns the limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError) as exc:
            log.warning("event=file_limit_not_raised soft=%d hard=%d error=%s", soft, hard, exc)
    return soft


def connections_allowed(file_limit: int) -> int:
    """How many HTTP connections the orchestrator takes at once with this file limit: all but a reserve
    of an eighth (at least 64) for its database, its ZeroMQ sockets and their peers' connections."""
    return max(16, file_limit - max(64, file_limit // 8))


class RateLog:
    """Logs an event the first time, then at most once per ``every_s`` with the count since."""

    def __init__(self, every_s: float = LOG_EVERY_S) -> None:
        self.every_s = every_s
        self._next: dict[str, float] = {}
        self._since: Counter[str] = Counter()

    def __call__(self, key: str, message: str, *args: Any) -> None:
        self._since[key] += 1
        now = time.monotonic()
        if now < self._next.get(key, 0.0):
            return
        self._next[key] = now + self.every_s
        log.warning(message + " count=%d", *args, self._since.pop(key))


class ConnectionLimits:
    """What every HTTP connection of one server shares: the bounds, the connections per peer, the counts."""

    def __init__(self, request_timeout_s: float, max_per_peer: int, max_total: int,
                 refused: Counter[str] | None = None) -> None:
        self.request_timeout_s = request_timeout_s
        self.max_per_peer = max_per_peer
        self.max_total = max_total
        self.per_peer: Counter[str] = Counter()
        self.total = 0
        self.refused: Counter[str] = Counter() if refused is None else refused  # connections closed, per reason
        self.rate_log = RateLog()

    def admit(self, peer: str) -> bool:
        """Takes a connection from ``peer``, or refuses it (counted and logged)."""
        reason = ("peer_limit" if self.per_peer[peer] >= self.max_per_peer else
                  "total_limit" if self.total >= self.max_total else "")
        if reason:
            self.refuse(reason, peer)
            return False
        self.per_peer[peer] += 1
        self.total += 1
        return True

    def release(self, peer: str) -> None:
        self.total -= 1
        self.per_peer[peer] -= 1
        if self.per_peer[peer] <= 0:
            del self.per_peer[peer]

    def refuse(self, reason: str, peer: str) -> None:
        self.refused[reason] += 1
        self.rate_log(reason, "event=http_connection_refused reason=%s peer=%s connections=%d max_per_peer=%d "
                              "max_total=%d", reason, peer, self.total, self.max_per_peer, self.max_total)


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol under :attr:`limits` (set by :func:`guarded_protocol`)."""

    limits: ClassVar[ConnectionLimits]
    _peer = ""
    _admitted = False
    _upgraded = False
    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._peer = self.client[0] if self.client else ""
        if not self.limits.admit(self._peer):
            transport.abort()
            return
        self._admitted = True
        self._watch_request()

    def connection_lost(self, exc: Exception | None) -> None:
        self._let_go()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        if not self._upgraded and not self.transport.is_closing():
            self._watch_request()

    def handle_websocket_upgrade(self, event: h11.Request) -> None:
        # the websocket protocol takes the transport over (and this one never hears of its end):
        # its request is whole, and the connection counts no longer here
        self._upgraded = True
        self._let_go()
        super().handle_websocket_upgrade(event)

    def _let_go(self) -> None:
        self._stop_watch()
        if self._admitted:
            self._admitted = False
            self.limits.release(self._peer)

    def _watch_request(self) -> None:
        """Arms the request's deadline while a request is being received, disarms it once it has come."""
        receiving = self.conn.their_state in (h11.IDLE, h11.SEND_BODY)
        if receiving and self._deadline is None:
            self._deadline = self.loop.call_later(self.limits.request_timeout_s, self._timed_out)
        elif not receiving:
            self._stop_watch()

    def _stop_watch(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _timed_out(self) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        if self.conn.their_state is h11.IDLE and self.conn.our_state is h11.IDLE:
            self.transport.write(TIMEOUT_RESPONSE)  # headers incomplete: nothing answered yet
        self.transport.close()
        self.limits.refuse("request_timeout", self._peer)


def guarded_protocol(limits: ConnectionLimits) -> type[H11Protocol]:
    """uvicorn's h11 protocol under ``limits``: pass it as ``uvicorn.Config(http=...)``."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {"limits": limits})


class AcceptBackoffLoop(asyncio.SelectorEventLoop):
    """asyncio's selector loop, whose accept loop stops at the first accept that fails for want of a
    file descriptor (asyncio already takes the listening socket's reader away then, and tries again a
    second later), and whose report of it is logged at a bounded rate, one line without a traceback."""

    def __init__(self) -> None:
        super().__init__()
        self.rate_log = RateLog()
        self.set_exception_handler(_handle_exception)

    def _accept_connection(self, protocol_factory: Any, sock: Any, *args: Any, **kwargs: Any) -> None:
        if isinstance(sock, _StopAfterResourceError):
            sock = sock.sock
        super()._accept_connection(protocol_factory, _StopAfterResourceError(sock),  # type: ignore[misc]
                                   *args, **kwargs)


def _handle_exception(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    exc = context.get("exception")
    if isinstance(loop, AcceptBackoffLoop) and isinstance(exc, OSError) and exc.errno in RESOURCE_ERRORS \
            and "accept" in str(context.get("message", "")):
        loop.rate_log("accept", "event=http_accept_failed error=%s (no connection taken for a second)",
                      exc.strerror or exc)
        return
    loop.default_exception_handler(context)


class _StopAfterResourceError:
    """The listening socket as asyncio's accept loop sees it: after an accept failed for want of a
    resource, the next says there is nothing more to accept, which ends the loop."""

    def __init__(self, sock: Any) -> None:
        self.sock = sock
        self._failed = False

    def accept(self) -> Any:
        if self._failed:
            raise BlockingIOError
        try:
            return self.sock.accept()
        except OSError as exc:
            self._failed = exc.errno in RESOURCE_ERRORS
            raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sock, name)

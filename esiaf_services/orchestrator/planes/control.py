"""The control plane: heartbeats in; out, the full state when it changed, else a short ack (ROUTER,
one JSON frame per message).

A message names its component (``component_id``) and carries the secret that component's current
registration was given (``control_key``): only then does it count as life, get an answer, and make
its routing id the one state is pushed to. Anyone else who holds the token or an allowed CURVE key
and knows a component id (``GET /components`` lists them) is refused, counted per reason and
logged, the first and every 100th. With CURVE, a registration is also bound to the public key of
its first accepted message. The ROUTER keeps libzmq's default for a routing id already connected:
the newcomer is ignored (no ROUTER_HANDOVER, which would let a peer naming a live routing id take
its pushes). See docs/protocol.md, "Control".

A component's process that dies closes its connection (its kernel does): the socket's monitor (the
ZAP guard's, zap.py: one per socket) says which file descriptor closed, each proven message which
descriptor it came on, and a component whose connection closed and that says nothing on a new one
within ``disconnect_grace_s`` is lost (:attr:`ControlPlane.on_lost`), without its ``dead_after_s``.
"""
from __future__ import annotations

import asyncio
import hmac
import logging
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any, cast

import zmq.asyncio

from esiaf.control_messages import (
    Ack,
    BeatNow,
    Command,
    Heartbeat,
    MessageError,
    State,
    Unknown,
    Unrecognised,
    encode,
    parse_to_orchestrator,
)

from ..registry.components import Component, Registry

log = logging.getLogger(__name__)

UNKNOWN = encode(Unknown())
BEAT_NOW = encode(BeatNow())
EVENTS, POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)  # plain ints: pyzmq's enums cost a microsecond a use


class ControlPlane:
    def __init__(self, socket: zmq.asyncio.Socket, registry: Registry, bind_peer_key: bool = False,
                 intervals_s: tuple[float, float] = (0.5, 0.5), disconnect_grace_s: float = 1.0, *,
                 on_lost: Callable[[Component], Awaitable[Any]] | None = None,
                 deadline_sooner: Callable[[], object] = lambda: None) -> None:
        """``on_lost``: called for a live component whose connection closed and that has not spoken
        since (its process died); ``deadline_sooner``: a component's death may be due sooner."""
        self.socket = socket
        # the same socket, used synchronously: run() takes every message there is when its file
        # descriptor wakes the loop, and send() never waits (a ROUTER drops what it cannot send)
        self._sync: zmq.Socket = zmq.Socket.shadow(socket.underlying)
        self._draining = False  # _drain() is taking messages: it looks at the socket again after each
        self._look_soon = False  # a _drain() is due (a send outside one read ZMQ_EVENTS)
        self.registry = registry
        self.bind_peer_key = bind_peer_key  # CURVE: the ZAP handler gives each message its peer's public key
        self.counters: Counter[str] = Counter()
        self.intervals_s = intervals_s  # the heartbeat interval, and the longest a component may say it beats at
        self.disconnect_grace_s = disconnect_grace_s
        self.on_lost = on_lost
        self._losing: set[asyncio.Task] = set()
        self.deadline_sooner = deadline_sooner

    async def run(self) -> None:
        """Takes and handles messages until cancelled. The socket's ZMQ_FD is registered with the loop
        once, not per message as zmq.asyncio's futures do (two epoll_ctl calls and a future each,
        a measurable share of a heartbeat's cost), and its callback handles every message there is at
        once, without waking a task (a future, a task step and one more turn of the loop per wake-up). ZMQ_FD is
        edge-triggered, and reading ZMQ_EVENTS, which any send does, resets it: so the socket is
        drained until it says it holds nothing, and looked at again after a send made outside a drain."""
        loop = asyncio.get_running_loop()
        fd: int = self._sync.FD
        loop.add_reader(fd, self._drain)
        self._drain()  # what came before
        try:
            await loop.create_future()  # the callback does the work
        finally:
            loop.remove_reader(fd)

    def _drain(self) -> None:
        """Handles every message the socket holds (the loop calls it when its file descriptor wakes)."""
        self._look_soon = False
        if self._sync.closed:  # a look asked for by a send just before the orchestrator stopped
            return
        self._draining = True
        try:
            while cast(int, self._sync.get(EVENTS)) & POLLIN:
                try:
                    frames = self._sync.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:  # libzmq may signal a message that is not there
                    self.counters["spurious_wakeups"] += 1
                    break
                try:
                    self.handle(frames)
                except Exception:  # a bug must not stop the heartbeats of everyone else
                    self.counters["errors"] += 1
                    log.exception("event=control_failed frames=%d", len(frames))
        finally:
            self._draining = False

    def disconnected(self, fd: int) -> None:
        """The connection on ``fd`` closed: the component whose key last came on it is lost unless it
        speaks again within the grace period (a connection redone: the SDK beats at once on a new one).
        It is asked to beat now, in case the connection its state goes to is a newer one on the same fd."""
        since = time.monotonic()
        for component in [c for c in self.registry.live.values() if c.control_fd == fd]:
            component.control_fd = None
            self.counters["disconnects"] += 1
            if component.control_route is not None:
                self._send(component.control_route, BEAT_NOW)
            asyncio.get_running_loop().call_later(self.disconnect_grace_s, self._maybe_lost, component, since)

    def _maybe_lost(self, component: Component, since: float) -> None:
        if self.registry.get(component.component_id) is not component or component.last_seen_mono >= since:
            return  # gone meanwhile, or it spoke
        log.info("event=control_disconnected component_id=%s grace_s=%g", component.component_id,
                 self.disconnect_grace_s)
        if self.on_lost is not None:
            task = asyncio.ensure_future(self.on_lost(component))
            self._losing.add(task)
            task.add_done_callback(self._losing.discard)

    def _bad(self, detail: str) -> None:
        """Counts a bad control message; logs the first and then every 100th."""
        self.counters["bad_messages"] += 1
        count = self.counters["bad_messages"]
        if count == 1 or count % 100 == 0:
            log.warning("event=bad_message plane=control count=%d %s", count, detail)

    def _refuse(self, reason: str, component: Component) -> None:
        """Counts a message refused for ``reason``; logs the first of each reason and every 100th."""
        self.counters["refused"] += 1
        key = f"refused_{reason}"
        self.counters[key] += 1
        if self.counters[key] == 1 or self.counters[key] % 100 == 0:
            log.warning("event=control_refused reason=%s component_id=%s count=%d", reason,
                        component.component_id, self.counters[key])

    def _proven(self, component: Component, message: Heartbeat | Unrecognised, data: zmq.Frame) -> bool:
        """The message carries the component's current control key (and, with CURVE, comes with the
        public key its registration is bound to); else it is refused and counted."""
        key = message.control_key
        if key is None:
            self._refuse("no_key", component)
            return False
        if not hmac.compare_digest(key.encode(), component.control_key.encode()):
            self._refuse("wrong_key", component)
            return False
        if self.bind_peer_key:
            peer_key = str(data.get("User-Id"))  # its public key, Z85: what the ZAP handler (pyzmq) names it
            if component.control_peer_key is None:
                component.control_peer_key = peer_key
            elif not hmac.compare_digest(peer_key.encode(), component.control_peer_key.encode()):
                self._refuse("wrong_peer_key", component)
                return False
        return True

    def handle(self, frames: list[zmq.Frame]) -> None:
        if len(frames) != 2:
            self._bad(f"frames={len(frames)}")
            return
        route, data = frames[0].bytes, frames[1]
        try:
            message = parse_to_orchestrator(data.bytes)
        except MessageError as exc:
            self._bad(f"route={route[:80]!r} reason={str(exc)!r}")
            return
        named = message.component_id
        component_id = named if named is not None else route.decode("utf-8", errors="replace")
        component = self.registry.get(component_id)
        if component is None:
            self.counters["unknown"] += 1
            log.debug("event=unknown_component component_id=%r", component_id[:80])
            self._send(route, UNKNOWN)
            return
        if not self._proven(component, message, data):
            return  # neither life nor an answer: whoever sent it does not hold this registration
        component.touch()
        component.control_route = route  # state goes to the connection that proved the key last
        fd = data.get(zmq.SRCFD)  # ... and the file descriptor it came on: its closing names it
        component.control_fd = fd if type(fd) is int and fd >= 0 else None
        if not isinstance(message, Heartbeat):
            self._bad(f"component_id={component.component_id} type={message.type[:50]!r}")
            return
        component.heartbeats += 1
        if message.stats is not None:
            component.stats = message.stats
        component.note_clock(message.clock)
        if component.beats_every(message.interval_s, *self.intervals_s):
            self.deadline_sooner()  # fast again: its death may be due before the liveness task wakes
        self.registry.offer_current(component)
        # its send time, echoed with ours: its clock's offset
        clock: dict[str, Any] = {} if message.sent_ns is None else {"echo_ns": message.sent_ns,
                                                                    "orchestrator_ns": time.time_ns()}
        # the state it says it has is the current one: a short ack; else (an older or no version) the full state
        if message.state_version is not None and message.state_version == component.state_version:
            self.counters["acks"] += 1
            self.send(component, Ack(version=component.state_version, **clock))
        else:
            self.send(component, self.versioned(component, **clock))

    @staticmethod
    def versioned(component: Component, **clock: int) -> State:
        """Its full state, numbered: the number its heartbeats give back once it has applied it."""
        state = component.pushed_state or State(peers={}, formats={})
        return state.model_copy(update={"version": component.state_version, **clock})

    async def push_changes(self) -> None:
        """Sends its new state to every live component whose peers or formats changed."""
        for component, _ in self.registry.changed_states():
            log.debug("event=state_pushed component_id=%s version=%d", component.component_id,
                      component.state_version)
            self.send(component, self.versioned(component))

    def send(self, component: Component, message: State | Ack | Command) -> None:
        # Only to the routing id that last presented the component's key; none yet: its first
        # heartbeat's answer carries the full state. ROUTER drops messages to a peer that is gone.
        if component.control_route is None:
            return
        self._send(component.control_route, encode(message))

    def _send(self, route: bytes, data: bytes) -> None:
        try:
            self._sync.send_multipart([route, data], zmq.NOBLOCK)
        except zmq.Again:  # its queue is full (ROUTER_MANDATORY is off: it drops, but to be sure)
            self.counters["dropped"] += 1
        if not self._draining and not self._look_soon:  # the send read ZMQ_EVENTS: a message that came
            self._look_soon = True  # meanwhile wakes no one; a drain under way looks again anyway
            asyncio.get_running_loop().call_soon(self._drain)

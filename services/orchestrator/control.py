"""The control plane: heartbeats in, full state out (ROUTER, one JSON frame per message)."""
from __future__ import annotations

import json
import logging
import time
from collections import Counter
from typing import Any

import zmq.asyncio

from .codec import MAX_TIME_NS
from .registry import Component, Registry

log = logging.getLogger(__name__)

UNKNOWN = json.dumps({"type": "unknown"}).encode()


class ControlPlane:
    def __init__(self, socket: zmq.asyncio.Socket, registry: Registry) -> None:
        self.socket = socket
        self.registry = registry
        self.counters: Counter[str] = Counter()

    async def run(self) -> None:
        while True:
            try:
                frames = await self.socket.recv_multipart()
            except zmq.Again:  # libzmq may signal a message that is not there
                self.counters["spurious_wakeups"] += 1
                continue
            try:
                await self.handle(frames)
            except Exception:  # a bug must not stop the heartbeats of everyone else
                self.counters["errors"] += 1
                log.exception("event=control_failed frames=%d", len(frames))

    def _bad(self, detail: str) -> None:
        """Counts a bad control message; logs the first and then every 100th."""
        self.counters["bad_messages"] += 1
        count = self.counters["bad_messages"]
        if count == 1 or count % 100 == 0:
            log.warning("event=bad_message plane=control count=%d %s", count, detail)

    async def handle(self, frames: list[bytes]) -> None:
        if len(frames) != 2:
            self._bad(f"frames={len(frames)}")
            return
        identity, data = frames
        component = self.registry.get(identity.decode("utf-8", errors="replace"))
        if component is None:
            self.counters["unknown"] += 1
            log.debug("event=unknown_component component_id=%r", identity[:80])
            await self.socket.send_multipart([identity, UNKNOWN])
            return
        component.touch()  # any message counts as life, even a malformed one
        try:
            message = json.loads(data)
            kind = message["type"]
        except (ValueError, KeyError, TypeError, RecursionError) as exc:
            self._bad(f"component_id={component.component_id} reason={str(exc)[:200]!r}")
            return
        if kind != "heartbeat":
            self._bad(f"component_id={component.component_id} type={str(kind)[:50]!r}")
            return
        component.heartbeats += 1
        stats = message.get("stats")
        if isinstance(stats, dict):
            component.stats = stats
        component.note_clock(message.get("clock"))
        state = self.registry.state_of(component)
        component.pushed_state = state
        sent_ns = message.get("sent_ns")
        if type(sent_ns) is int and abs(sent_ns) < MAX_TIME_NS:  # its send time, echoed with ours: its clock's offset
            await self.send(component, {**state, "echo_ns": sent_ns, "orchestrator_ns": time.time_ns()})
        else:
            await self.send(component, state)

    async def push_changes(self) -> None:
        """Sends its new state to every live component whose peers or formats changed."""
        for component, state in self.registry.changed_states():
            log.debug("event=state_pushed component_id=%s", component.component_id)
            await self.send(component, state)

    async def send(self, component: Component, message: dict[str, Any]) -> None:
        # ROUTER drops messages to a peer that is not (yet) connected: the next heartbeat's
        # answer carries the full state anyway.
        await self.socket.send_multipart([component.component_id.encode(),
                                          json.dumps(message).encode()])

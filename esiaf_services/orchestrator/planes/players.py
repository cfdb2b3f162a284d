"""The robots' players, per stream: orders sent to a stream's player over the control plane, what it
plays (its heartbeat's ``playing``), the stream's barge-in policy, and barge-in events.

A player is a live component whose kind is ``playback`` and whose ``stream_id`` is the stream's (each
robot its own). Orders travel as :class:`esiaf.control_messages.Command` to the connection its key last
came on. A person who starts speaking while the robot plays (the vad's ``speech_start`` result inside a
playback span, fusion/playback.py) is a barge-in: a ``{"type": "barge_in", ...}`` event for the
websocket clients of the stream, and a :class:`~esiaf.control_messages.BargeIn` order carrying the
stream's policy (``stop``, ``duck`` or ``ignore``) for its player.
"""
from __future__ import annotations

import json
import logging
import time
from typing import Any, get_args

from esiaf.control_messages import BargeIn, BargeInPolicy, Command, PlayerOrder

from ..fusion.playback import PLAYBACK, Played
from ..registry.components import Component, Registry
from ..store.database import Store
from .control import ControlPlane
from .hub import Outgoing

log = logging.getLogger(__name__)


class NoPlayer(Exception):
    """The stream has no player that can take an order: ``status`` is the HTTP status (404: none
    registered for it; 409: one registered that has not connected its control channel yet)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class Players:
    def __init__(self, registry: Registry, control: ControlPlane, default_policy: BargeInPolicy = "stop",
                 store: Store | None = None) -> None:
        self.registry = registry
        self.control = control
        self.default_policy: BargeInPolicy = default_policy
        self.store = store
        # streams whose policy was set (PUT /streams/{s}/barge-in), kept in the store across restarts
        self.policies: dict[str, BargeInPolicy] = {}
        if store is not None:
            known = get_args(BargeInPolicy)
            self.policies = {stream: policy for stream, policy in store.policies().items()  # type: ignore[misc]
                             if policy in known}
        self.barge_ins = 0

    def set_policy(self, stream_id: str, policy: BargeInPolicy) -> None:
        """Sets a stream's policy, stored first (sqlite3.Error if the database cannot be written: then unchanged)."""
        if self.store is not None:
            self.store.put_policy(stream_id, policy, time.time_ns())
        self.policies[stream_id] = policy

    def player_of(self, stream_id: str) -> Component:
        """The live player of ``stream_id`` (the latest registered); NoPlayer if there is none."""
        players = [c for c in self.registry.live.values() if c.kind == PLAYBACK and c.stream_id == stream_id]
        if not players:
            raise NoPlayer(404, f"no player plays stream {stream_id!r}: none is registered for it "
                                "(start one: esiaf run --player, or python -m esiaf_services.player)")
        player = max(players, key=lambda c: c.registered_ns)
        if player.control_route is None:
            raise NoPlayer(409, f"the player of stream {stream_id!r} ({player.component_id}) has not connected "
                                "its control channel yet; try again in a moment")
        return player

    def order(self, stream_id: str, order: PlayerOrder) -> Component:
        """Sends ``order`` to the stream's player; NoPlayer if it has none."""
        player = self.player_of(stream_id)
        self.control.send(player, Command(stream_id=stream_id, order=order))
        log.info("event=player_order stream_id=%s order=%s component_id=%s", stream_id, order.action,
                 player.component_id)
        return player

    def playing(self, stream_id: str) -> tuple[Component, dict[str, Any] | None]:
        """The stream's player and what it plays now (its last heartbeat's ``playing``), if anything."""
        player = self.player_of(stream_id)
        info = (player.stats or {}).get("info")
        playing = info.get("playing") if isinstance(info, dict) else None
        return player, playing if isinstance(playing, dict) else None

    def policy(self, stream_id: str) -> BargeInPolicy:
        return self.policies.get(stream_id, self.default_policy)

    def barge_in(self, stream_id: str, capture_ns: int, item: Played, direction_deg: float | None) -> Outgoing:
        """A person started speaking at ``capture_ns`` while ``item`` played: its player is told (under the
        stream's policy), and the event to send on the websocket is returned."""
        policy = self.policy(stream_id)
        self.barge_ins += 1
        if policy != "ignore":
            try:
                self.order(stream_id, BargeIn(policy=policy, capture_ns=capture_ns))
            except NoPlayer as exc:
                log.info("event=barge_in_unapplied stream_id=%s reason=%s", stream_id, exc)
        event: dict[str, Any] = {"type": "barge_in", "stream_id": stream_id, "capture_ns": capture_ns,
                                 "playing": item.name, "policy": policy}
        if direction_deg is not None:
            event["direction_deg"] = round(direction_deg, 1)
        log.info("event=barge_in stream_id=%s capture_ns=%d policy=%s", stream_id, capture_ns, policy)
        return Outgoing(text=json.dumps(event, separators=(",", ":")), stream_id=stream_id)

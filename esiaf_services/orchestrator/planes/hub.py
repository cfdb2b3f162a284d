"""Fan-out of fused results, stream events and partial results to websocket clients.

Publishing never waits: each client has its own bounded queue, drained by its
own task. A client that falls more than ``max_queue`` messages behind is
dropped from the hub and told why when its connection is closed, so a slow
client never holds up the others or the ingest.
"""
from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass

log = logging.getLogger(__name__)

MAX_QUEUE = 1000  # messages a websocket client may fall behind before it is closed
CLOSE_TOO_SLOW = 1008  # policy violation; 1013 ("try again later") is not allowed in all clients


@dataclass(frozen=True)
class Outgoing:
    """One message for websocket clients, already encoded once for all of them."""

    text: str
    stream_id: str
    fusion: str | None = None  # None: a stream event, sent whatever the client's fusion filter
    fused_id: int | None = None
    revision: int = 0
    seq: int = 0  # publication number of a fused result (every revision has its own)
    partial: bool = False  # a partial result's event (partials.py): only to clients that asked for them
    robot: bool = False  # a fused result of the robot's own voice: only to clients that include it...
    withdrawal: str = ""  # ... and to the others this instead, where they had its previous revision (a person's)

    def text_for(self, include_robot: bool) -> str:
        return self.withdrawal if self.robot and not include_robot else self.text


WITHDRAWAL_FIELDS = {"id", "revision", "seq", "fusion", "stream_id"}


def withdrawal(fused: dict) -> str:
    """The event that withdraws a fused result sent as a person's, from its revision that is the robot's
    (its fields of WITHDRAWAL_FIELDS; docs/protocol.md)."""
    return json.dumps({"type": "fused_withdrawn", **{k: fused[k] for k in sorted(WITHDRAWAL_FIELDS)},
                       "source": "robot"})


class Subscriber:
    def __init__(self, name: str, stream: str | None, fusion: str | None, max_queue: int,
                 partials: bool = False, include_robot: bool = False) -> None:
        self.name = name
        self.stream = stream
        self.fusion = fusion
        self.partials = partials
        self.include_robot = include_robot
        self.queue: asyncio.Queue[Outgoing] = asyncio.Queue(maxsize=max_queue)
        self.dropped = asyncio.Event()  # set when the hub gave up on this client
        self.close_reason = ""

    def wants(self, message: Outgoing) -> bool:
        if self.stream is not None and message.stream_id != self.stream:
            return False
        if message.partial and not self.partials:
            return False
        if message.robot and not self.include_robot and not message.withdrawal:
            return False
        return message.fusion is None or self.fusion is None or message.fusion == self.fusion


class Hub:
    def __init__(self, max_queue: int = MAX_QUEUE) -> None:
        self.max_queue = max_queue
        self._subscribers: set[Subscriber] = set()
        self.dropped_clients = 0

    def subscribe(self, name: str, stream: str | None = None,
                  fusion: str | None = None, partials: bool = False, include_robot: bool = False) -> Subscriber:
        subscriber = Subscriber(name, stream, fusion, self.max_queue, partials, include_robot)
        self._subscribers.add(subscriber)
        return subscriber

    def unsubscribe(self, subscriber: Subscriber) -> None:
        self._subscribers.discard(subscriber)

    def __len__(self) -> int:
        return len(self._subscribers)

    def depths(self) -> list[int]:
        """How many messages each client's queue holds."""
        return [subscriber.queue.qsize() for subscriber in self._subscribers]

    def publish(self, message: Outgoing) -> None:
        """Queues ``message`` for every interested client; never blocks."""
        for subscriber in list(self._subscribers):
            if not subscriber.wants(message):
                continue
            try:
                subscriber.queue.put_nowait(message)
            except asyncio.QueueFull:
                self._drop(subscriber)

    def _drop(self, subscriber: Subscriber) -> None:
        self._subscribers.discard(subscriber)
        self.dropped_clients += 1
        subscriber.close_reason = (f"too slow: fell more than {self.max_queue} messages behind; "
                                   "reconnect with after_id")
        while not subscriber.queue.empty():  # free the memory now, the client is gone
            subscriber.queue.get_nowait()
        subscriber.dropped.set()
        log.warning("event=ws_client_dropped client=%s reason=too_slow max_queue=%d",
                    subscriber.name, self.max_queue)

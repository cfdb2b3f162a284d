"""The results plane's socket loop: PULL what components send, in batches of what is already
waiting (at most ``MAX_BATCH``), and hand each batch to the ingest pipeline (ingest.py)."""
from __future__ import annotations

import asyncio
import logging
from collections import Counter
from typing import Any, cast

import zmq
import zmq.asyncio

from .binding import peer_key
from .ingest import Ingest

log = logging.getLogger(__name__)

MAX_BATCH = 64  # messages handled per transaction


class ResultsLoop:
    def __init__(self, socket: zmq.asyncio.Socket, ingest: Ingest, *, bind_peer_key: bool = False) -> None:
        self.socket = socket
        self.ingest = ingest
        self.bind_peer_key = bind_peer_key  # CURVE: each message comes with its peer's public key
        self.counters: Counter[str] = Counter()

    async def run(self) -> None:
        self.ingest.arm_timer()  # fusions restored from the database may be due
        while True:
            try:
                batch: list[Any] = [await self.socket.recv_multipart(copy=not self.bind_peer_key)]
            except zmq.Again:  # libzmq may signal a message that is not there (seen with heartbeats)
                self.counters["spurious_wakeups"] += 1
                if self.counters["spurious_wakeups"] in (1, 100, 10_000):
                    log.info("event=spurious_wakeup plane=results count=%d", self.counters["spurious_wakeups"])
                continue
            while len(batch) < MAX_BATCH and cast(int, self.socket.get(zmq.EVENTS)) & zmq.POLLIN:
                try:
                    batch.append(cast("asyncio.Future[list[Any]]", self.socket.recv_multipart(
                        zmq.NOBLOCK, copy=not self.bind_peer_key)).result())
                except zmq.Again:
                    break
            if self.bind_peer_key:  # CURVE: frames (copy=False) carry their peer's public key
                self.ingest.handle_batch([[f.bytes for f in frames] for frames in batch], [peer_key(f) for f in batch])
            else:
                self.ingest.handle_batch(batch)

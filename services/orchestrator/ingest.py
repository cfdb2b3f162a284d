"""The results plane: PULL → store → fuse → publish.

Messages that are already waiting are handled as one batch in one transaction;
everything is stored (and committed) before anything of the batch is published.
"""
from __future__ import annotations

import json
import logging
import time
from collections import Counter
from typing import Any, Callable

import zmq
import zmq.asyncio

from .codec import BadResult, parse_result, result_to_json, type_name
from .fusion import FusedResult, FusionEngine, StoredResult
from .hub import Hub, Outgoing
from .registry import Registry
from .store import Store
from .streams import StreamEnds

log = logging.getLogger(__name__)

MAX_BATCH = 64  # messages handled per transaction


def _dumps(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


class Ingest:
    def __init__(self, socket: zmq.asyncio.Socket, store: Store, engine: FusionEngine, hub: Hub,
                 registry: Registry, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.socket = socket
        self.store = store
        self.engine = engine
        self.hub = hub
        self.registry = registry
        self.streams = StreamEnds()
        self.counters: Counter[str] = Counter()
        self._clock_ns = clock_ns

    async def run(self) -> None:
        while True:
            batch = [await self.socket.recv_multipart()]
            while len(batch) < MAX_BATCH and self.socket.get(zmq.EVENTS) & zmq.POLLIN:
                batch.append(await self.socket.recv_multipart())
            self.handle_batch(batch)

    def handle_batch(self, batch: list[list[bytes]]) -> None:
        outgoing: list[Outgoing] = []
        try:
            self.store.begin()
            for frames in batch:
                outgoing.extend(self._handle(frames))
            self.store.commit()
        except Exception:
            self.store.rollback()
            self.counters["lost_in_db_error"] += len(batch)
            log.exception("event=store_failed messages=%d", len(batch))
            return
        self._publish(outgoing)

    def components_gone(self, names: list[str]) -> None:
        """Fusions and stream ends stop waiting for components that died or left."""
        outgoing: list[Outgoing] = []
        try:
            self.store.begin()
            for name in names:
                outgoing.extend(self._store_fused(f) for f in self.engine.on_component_gone(name))
            self.store.commit()
        except Exception:
            self.store.rollback()
            outgoing = []
            log.exception("event=store_failed after=components_gone")
        self._publish(outgoing + self.stream_ends())

    def _publish(self, outgoing: list[Outgoing]) -> None:
        for message in outgoing:
            self.hub.publish(message)

    def _handle(self, frames: list[bytes]) -> list[Outgoing]:
        kind = frames[0] if frames else b""
        if kind == b"result" and len(frames) == 2:
            return self._on_result(frames[1])
        if kind == b"end_of_stream" and len(frames) == 2:
            return self._on_end_of_stream(frames[1])
        self.counters["bad_messages"] += 1
        log.warning("event=bad_message plane=results kind=%r frames=%d", kind[:40], len(frames))
        return []

    def _on_result(self, data: bytes) -> list[Outgoing]:
        received_ns = self._clock_ns()
        try:
            result = parse_result(data)
            result_id = self.store.next_result_id
            as_json = result_to_json(result, result_id, received_ns)
            text = _dumps(as_json)
        except (BadResult, ValueError) as exc:
            self.counters["bad_results"] += 1
            log.warning("event=bad_result reason=%r", str(exc))
            return []
        self.store.allocate_result_id()
        kind = type_name(result)
        self.store.add_result(
            result_id=result_id, component=result.component, type_name=kind,
            stream_id=result.stream_id, start_ns=result.span.start_ns, end_ns=result.span.end_ns,
            produced_ns=result.produced_ns, received_ns=received_ns, proto=data, json_text=text)
        self.counters["results"] += 1
        component = self.registry.by_name(result.component)
        if component is not None:  # any message counts as life
            component.touch()
            component.results_received += 1
        self.streams.on_result(result.stream_id)
        stored = StoredResult(id=result_id, component=result.component, type=kind,
                              stream_id=result.stream_id, start_ns=result.span.start_ns,
                              end_ns=result.span.end_ns, json=as_json)
        return [self._store_fused(fused) for fused in self.engine.on_result(stored)]

    def _store_fused(self, fused: FusedResult) -> Outgoing:
        text = _dumps(fused.json)
        self.store.add_fused(fused_id=fused.id, revision=fused.revision, fusion=fused.fusion,
                             stream_id=fused.stream_id, start_ns=fused.start_ns,
                             end_ns=fused.end_ns, published_ns=fused.published_ns, json_text=text)
        self.counters["fused"] += 1
        return Outgoing(text=text, stream_id=fused.stream_id, fusion=fused.fusion,
                        fused_id=fused.id, revision=fused.revision)

    def _on_end_of_stream(self, data: bytes) -> list[Outgoing]:
        try:
            message = json.loads(data)
            component_id, stream_id = message["component_id"], message["stream_id"]
            if not isinstance(component_id, str) or not isinstance(stream_id, str):
                raise TypeError("component_id and stream_id must be strings")
        except (ValueError, KeyError, TypeError) as exc:
            self.counters["bad_messages"] += 1
            log.warning("event=bad_end_of_stream reason=%r data=%r", str(exc), data[:200])
            return []
        component = self.registry.get(component_id)
        if component is not None:
            component.touch()
        log.info("event=end_of_stream component_id=%s stream_id=%s", component_id, stream_id)
        self.streams.on_end_of_stream(stream_id, component_id)
        return self.stream_ends()

    def stream_ends(self) -> list[Outgoing]:
        """``stream_end`` events of the streams that have now ended (call after any change)."""
        ended = self.streams.finished(c.component_id for c in self.registry.with_inputs())
        for stream_id in ended:
            log.info("event=stream_end stream_id=%s", stream_id)
        return [Outgoing(text=_dumps({"type": "stream_end", "stream_id": stream_id}),
                         stream_id=stream_id) for stream_id in ended]

"""The results plane's pipeline: store → fuse → publish, one batch in one transaction.

A batch (what the socket loop, results.py, found waiting) is handled in one transaction;
everything is stored (and committed) before anything of the batch is published. While the
database cannot be written, the writes stay queued and are retried; fused results still go out.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

from esiaf.proto import esiaf_pb2 as pb

from ..fusion.engine import FusionEngine, Publication, StoredResult
from ..fusion.orphans import Orphans
from ..fusion.playback import SELF, SPEECH_START, Played
from ..registry.components import Component, Registry
from ..registry.streams import StreamEnds
from ..store.database import Store, StoreUnavailable
from ..store.warmstart import restore
from .binding import refusal
from .clocks import StreamClocks
from .codec import BadResult, parse_result, result_to_json, type_name
from .hub import WITHDRAWAL_FIELDS, Hub, Outgoing, withdrawal
from .metrics import Metrics
from .partials import PARTIAL_KIND, Partials

log = logging.getLogger(__name__)

MAX_NOTICE_BYTES = 4096  # an end_of_stream notice
STORE_RETRY_S = 1.0  # while the database cannot be written: how often queued writes are retried
OVERHEAD_SAMPLES = 10_000


def _dumps(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


class Ingest:
    def __init__(self, store: Store, engine: FusionEngine, hub: Hub, registry: Registry, *,
                 clocks: StreamClocks | None = None, clock_ns: Callable[[], int] = time.time_ns,
                 metrics: Metrics | None = None, stream_end_grace_s: float = 0.0, stream_end_stall_grace_s: float = 0.0,
                 on_assignments_changed: Callable[[], None] = lambda: None) -> None:
        """``on_assignments_changed``: called when a stream became active or ended, so that the
        replicas' states are pushed."""
        self.store = store
        self.engine = engine
        self.orphans = Orphans(engine)  # what dead recogniser instances left unanswered
        self.partials = Partials()  # what recognisers heard of utterances still going on: sent, not stored
        self.hub = hub
        self.registry = registry
        self.streams = StreamEnds()
        self.stream_end_grace_ns = int(stream_end_grace_s * 1e9)
        self.stream_end_stall_grace_ns = int(stream_end_stall_grace_s * 1e9)
        self.counters: Counter[str] = Counter()
        self._clock_ns = clock_ns
        self._timer: asyncio.TimerHandle | None = None
        self._timer_ns: int | None = None
        # fusion overhead: the completing result's reception -> its fused result handed to
        # the websocket clients (revision 1 only), the last OVERHEAD_SAMPLES of them
        self.overhead_ns: deque[int] = deque(maxlen=OVERHEAD_SAMPLES)
        # timed-out fusions: their deadline -> fused result handed to the websocket clients
        self.timer_lateness_ns: deque[int] = deque(maxlen=OVERHEAD_SAMPLES)
        self._triggers: dict[Outgoing, tuple[deque[int], int]] = {}
        self.metrics = metrics
        # latencies (histogram, labels, seconds) of this transaction: observed once it is committed
        self._observed: list[tuple[Any, tuple[str, ...], float]] = []
        self.clocks = clocks or StreamClocks(registry)
        self._store_retry: asyncio.TimerHandle | None = None
        self._on_assignments_changed = on_assignments_changed
        # a person started speaking while the stream's robot played: (stream, onset, what played, direction)
        # -> the barge_in event to publish (planes/players.py)
        self.on_barge_in: Callable[[str, int, Played, float | None], Outgoing] | None = None

    def restore(self) -> None:
        """Warm start from the database (store/warmstart.py)."""
        restore(self.store, self.engine, self.registry, self.on_stream_announced)

    def handle_batch(self, batch: list[list[bytes]], peer_keys: list[str | None] | None = None) -> None:
        """``peer_keys``: with CURVE, the public key each message came with."""
        keys = peer_keys or [None] * len(batch)

        def work() -> list[Outgoing]:
            return [message for frames, key in zip(batch, keys, strict=True) for message in self._isolated(frames, key)]
        self._transaction(work, lost=len(batch), after="batch")

    def _isolated(self, frames: list[bytes], peer_key: str | None = None) -> list[Outgoing]:
        """One message in a savepoint of the batch's transaction: if handling it fails, it alone
        is undone and refused (counted with its reason); its neighbours are stored."""
        mark = self.store.savepoint()
        counters = self.counters.copy()
        observed = len(self._observed)
        try:
            outgoing = self._handle(frames, peer_key)
        except Exception as exc:  # a poison message must not take its batch with it
            self.store.rollback_savepoint(mark)
            self.counters = counters
            del self._observed[observed:]
            self._refuse("handler_error", f"{type(exc).__name__}: {exc}")
            return []
        return outgoing

    def on_stream_announced(self, stream_id: str, source: str, info: dict[str, Any]) -> None:
        """A source said what it plays: its capture times are on ``source``'s clock (corrected by its
        offset, clocks.py), and a replay faster than real time (``"realtime": false``)
        does not teach the fusion its components' latencies."""
        if source:
            self.clocks.announce(stream_id, source)
        if isinstance(info, dict) and info.get("realtime") is False:
            self.engine.mark_replayed(stream_id)

    def _refuse(self, reason: str, detail: str) -> None:
        """Counts a refused message by reason; logs the first and then every 100th of a reason."""
        self.counters["refused"] += 1
        key = f"refused_{reason}"
        self.counters[key] += 1
        if self.counters[key] == 1 or self.counters[key] % 100 == 0:
            log.warning("event=message_refused reason=%s count=%d detail=%.300s", reason, self.counters[key], detail)

    def components_gone(self, gone: list[Component]) -> None:
        """Fusions and stream ends stop waiting for components that died or left; what a dead one
        left unanswered on the streams it served is fused without it (fusion/orphans.py)."""
        def work() -> list[Outgoing]:
            now_ns = self._clock_ns()
            return [self._store_fused(f) for c in gone for f in [
                *self.engine.on_component_gone(c.name),
                *(f for s in c.served_at_departure if c.status == "dead" for f in self.orphans.on_death(
                    s, c.name, c.kind, now_ns - self.clocks.capture_offset_ns(s), now_ns))]]
        self._transaction(work, after="components_gone")
        self._publish(self.stream_ends())

    def check_stream_ends(self) -> None:
        """Publishes the ends of streams that were held for a component that has not come back."""
        self._publish(self.stream_ends())

    def on_timer(self) -> None:
        """The earliest fusion deadline has come: publish what is due."""
        self._timer = None
        self._transaction(lambda: [self._store_fused(f) for f in self.engine.on_timer()],
                          after="timer")

    def _transaction(self, work: Callable[[], list[Outgoing]], *, lost: int = 0,
                     after: str) -> None:
        """Runs ``work`` in one transaction with what fusion must record, then publishes what
        it returned (nothing is published before it is committed); re-arms the timer."""
        counters = self.counters.copy()  # what a rolled-back transaction counted did not happen
        try:
            self.store.begin()
            outgoing = work()
            self._record_fusion_changes()
            self.store.commit()
        except StoreUnavailable:
            # the disk is full or the file read-only: the writes stay queued (bounded) and are
            # retried; the fused results still go out, a robot must not go deaf for its disk
            self._retry_store_later()
        except Exception:
            self.store.rollback()
            self._triggers.clear()
            self._observed.clear()
            self.counters = counters
            self.counters["lost_in_db_error"] += lost
            log.exception("event=store_failed after=%s messages=%d", after, lost)
            outgoing = []
        self._observe()
        self._publish(outgoing)
        self.arm_timer()

    def _observe(self) -> None:
        if self.metrics is not None:
            for histogram, labels, seconds in self._observed:
                histogram.labels(*labels).observe(seconds)
        self._observed.clear()

    def _retry_store_later(self) -> None:
        if self._store_retry is None:
            self._store_retry = asyncio.get_running_loop().call_later(STORE_RETRY_S, self._retry_store)

    def _retry_store(self) -> None:
        self._store_retry = None
        try:
            self.store.commit()
        except StoreUnavailable:
            self._retry_store_later()

    def _record_fusion_changes(self) -> None:
        changes = self.engine.changes
        now_ns = self._clock_ns()
        for fusion, received_ns in changes.opened:
            if fusion.id in self.engine.open:
                self.store.add_pending(
                    fused_id=fusion.id, anchor_id=fusion.anchor.id,
                    settings_json=fusion.settings.model_dump_json(),
                    waiting_json=_dumps(fusion.waiting), opened_ns=received_ns)
        opened = {fusion.id for fusion, _ in changes.opened}
        for fused_id in changes.closed:
            if fused_id not in opened:  # opened and closed in one transaction: never written
                self.store.remove_pending(fused_id)
        changes.opened.clear()
        changes.closed.clear()
        for component, latency in self.engine.latencies.take_changed():
            self.store.put_latency(component=component, count=latency.count,
                                   mean_ns=latency.mean_ns, updated_ns=now_ns)

    def arm_timer(self) -> None:
        deadline_ns = self.engine.next_deadline_ns()
        if deadline_ns == self._timer_ns and self._timer is not None:
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_ns = deadline_ns
        if deadline_ns is not None:
            delay_s = max(0.0, (deadline_ns - self._clock_ns()) / 1e9)
            self._timer = asyncio.get_running_loop().call_later(delay_s, self.on_timer)

    def _publish(self, outgoing: list[Outgoing]) -> None:
        for message in outgoing:
            self.hub.publish(message)
        if outgoing:
            now_ns = self._clock_ns()
            for message in outgoing:
                samples, since_ns = self._triggers.pop(message, (None, 0))
                if samples is not None:
                    samples.append(now_ns - since_ns)
                    if self.metrics is not None:
                        histogram = (self.metrics.fusion_overhead if samples is self.overhead_ns
                                     else self.metrics.timer_lateness)
                        histogram.observe((now_ns - since_ns) / 1e9)

    def _handle(self, frames: list[bytes], peer_key: str | None) -> list[Outgoing]:
        kind = frames[0] if frames else b""
        if kind == b"result" and len(frames) in (2, 4):
            return self._on_result(frames, peer_key)
        if kind == b"end_of_stream" and len(frames) in (2, 4):
            return self._on_end_of_stream(frames, peer_key)
        self.counters["bad_messages"] += 1
        self._refuse("bad_frames", f"kind={kind[:40]!r} frames={len(frames)}")
        return []

    def _proven(self, frames: list[bytes], component_id: str, peer_key: str | None) -> bool:
        """The message comes from ``component_id``'s registration (binding.py); else refused, counted."""
        reason = refusal(self.registry, frames, component_id, peer_key)
        if reason is not None:
            self._refuse(reason, f"kind={frames[0]!r} component_id={component_id[:80]!r}")
        return reason is None

    def _on_result(self, frames: list[bytes], peer_key: str | None) -> list[Outgoing]:
        received_ns, data = self._clock_ns(), frames[1]
        try:
            result = parse_result(data, self.clocks.reference_ns)
            result_id = self.store.next_result_id
            as_json = result_to_json(result, result_id, received_ns, self.clocks.capture_offset_ns(result.stream_id))
            text = _dumps(as_json)
        except (BadResult, ValueError) as exc:
            self.counters["bad_results"] += 1
            self._refuse("bad_result", str(exc))
            return []
        if not self._proven(frames, result.instance, peer_key):
            return []  # neither stored nor fused nor life: not its registration's
        kind = type_name(result)
        if kind == PARTIAL_KIND:
            return self._on_partial(result, received_ns)
        self.store.allocate_result_id()
        closed = self.partials.on_result(result, received_ns)  # its final closes its partial
        self.store.add_result(
            result_id=result_id, component=result.component, type_name=kind,
            stream_id=result.stream_id, start_ns=result.span.start_ns, end_ns=result.span.end_ns,
            produced_ns=result.produced_ns, received_ns=received_ns, proto=data, json_text=text)
        component = self.registry.get(result.instance)
        if component is not None:  # any message counts as life
            component.touch()
            component.results_received += 1
        if self.registry.add_stream(result.stream_id, component):
            self._on_assignments_changed()  # an unannounced stream: it is served from now on
        self.streams.on_result(result.stream_id)
        self.clocks.remember(result.stream_id, result.span.start_ns)
        stored = StoredResult(id=result_id, component=result.component, type=kind,
                              stream_id=result.stream_id, start_ns=result.span.start_ns,
                              end_ns=result.span.end_ns, json=as_json)
        outgoing = self._barge_in(stored) if kind == SPEECH_START else []
        outgoing += [self._store_fused(fused) for fused in [
            *self.orphans.before_result(stored, received_ns), *self.engine.on_result(stored, received_ns),
            *self.orphans.on_result(stored, received_ns),
            *self.orphans.on_segment(stored, received_ns, lambda service: bool(self.registry.instances(service)))]]
        if closed is not None:
            outgoing.insert(0, closed)
        self.counters["results"] += 1  # stored and fused: counted once nothing can undo it
        if self.metrics is not None:
            self._observed.append((self.metrics.result_latency, (result.component, result.stream_id),
                                   as_json["latency_ms"] / 1e3))
        return outgoing

    def _on_partial(self, result: pb.Result, received_ns: int) -> list[Outgoing]:
        """A partial result: life for its component, an event for the websocket; never stored or fused."""
        component = self.registry.get(result.instance)
        if component is not None:
            component.touch()
        self.counters["partials"] += 1
        return [self.partials.on_partial(result, received_ns)]

    def _barge_in(self, speech_start: StoredResult) -> list[Outgoing]:
        """A vad's speech start (span: onset, decision): a barge-in if the stream's robot was playing then,
        unless the localiser heard it come from the robot's own loudspeaker (ssl's ``self``)."""
        onset_ns = speech_start.start_ns
        item = self.engine.playing_at(speech_start.stream_id, onset_ns)
        if item is None or self.on_barge_in is None:
            return []
        talker = self.engine.talker(speech_start.stream_id, onset_ns, max(speech_start.end_ns, onset_ns + 1))
        if talker is not None and talker.get("source_id") == SELF:
            self.counters["barge_ins_from_self"] += 1
            return []
        direction = None if talker is None or talker.get("background") else float(talker["azimuth_deg"])
        return [self.on_barge_in(speech_start.stream_id, onset_ns, item, direction)]

    def _store_fused(self, fused: Publication) -> Outgoing:
        seq = fused.result.seq = self.store.allocate_seq()
        text = fused.result.to_json()  # serialised once: stored, served and sent as this text
        self.store.add_fused(fused_id=fused.id, revision=fused.revision, fusion=fused.fusion,
                             stream_id=fused.stream_id, start_ns=fused.start_ns,
                             end_ns=fused.end_ns, published_ns=fused.published_ns, json_text=text,
                             seq=seq)
        self.counters["fused"] += 1
        self.counters[f"completion_{fused.result.completion}" if fused.revision == 1
                      else "revisions"] += 1
        message = Outgoing(text=text, stream_id=fused.stream_id, fusion=fused.fusion,
                           fused_id=fused.id, revision=fused.revision, seq=seq, robot=fused.result.source == "robot",
                           withdrawal=withdrawal(fused.result.model_dump(include=WITHDRAWAL_FIELDS))
                           if fused.withdraws else "")
        anchor_received_ns = fused.result.anchor.get("received_ns")
        if self.metrics is not None and fused.revision == 1 and isinstance(anchor_received_ns, int):
            labels = (fused.fusion, fused.stream_id, fused.result.completion)
            self._observed.append((self.metrics.fused_latency, labels, (fused.published_ns - anchor_received_ns) / 1e9))
        if fused.revision == 1 and fused.trigger_received_ns is not None:
            self._triggers[message] = (self.overhead_ns, fused.trigger_received_ns)
        elif fused.revision == 1 and fused.due_ns is not None:
            self._triggers[message] = (self.timer_lateness_ns, fused.due_ns)
        return message

    def _on_end_of_stream(self, frames: list[bytes], peer_key: str | None) -> list[Outgoing]:
        data = frames[1]
        try:
            if len(data) > MAX_NOTICE_BYTES:
                raise ValueError(f"{len(data)} bytes, more than {MAX_NOTICE_BYTES}")
            message = json.loads(data)
            component_id, stream_id = message["component_id"], message["stream_id"]
            if not isinstance(component_id, str) or not isinstance(stream_id, str):
                raise TypeError("component_id and stream_id must be strings")
        except (ValueError, KeyError, TypeError, RecursionError) as exc:
            self.counters["bad_messages"] += 1
            self._refuse("bad_end_of_stream", f"{type(exc).__name__}: {exc} data={data[:100]!r}")
            return []
        if not self._proven(frames, component_id, peer_key):
            return []
        component = self.registry.get(component_id)
        fused: list[Outgoing] = []
        if component is not None:
            component.touch()
            fused = [self._store_fused(f) for f in [
                *self.engine.on_end_of_stream(stream_id, component.name),
                *self.orphans.on_end_of_stream(stream_id, component.name, component.kind, self._clock_ns())]]
            service: str | None = component.name
        else:  # said by an instance since declared dead, or one we never knew: its service, if known
            departed = self.registry.departed.get(component_id)
            service = departed.name if departed is not None else None
        log.info("event=end_of_stream component_id=%s stream_id=%s", component_id, stream_id)
        if service is not None:
            self.streams.on_end_of_stream(stream_id, service)
        return fused + self.stream_ends()  # the stream's last fused results before its end

    def held_until_ns(self, component: Component) -> float | None:
        """Until when ``component``, dead, may hold the end of a stream it has not ended:
        ``stream_end_stall_grace_s`` after its death if it went silent (stalled: it may come back with its
        backlog), ``stream_end_grace_s`` if it was seen to die (for a restarted instance); None if alive."""
        return component.holds_stream_end_until_ns(self.stream_end_grace_ns, self.stream_end_stall_grace_ns)

    def stream_ends(self) -> list[Outgoing]:
        """``stream_end`` events of the streams that have now ended (call after any change): every
        service with a live instance with inputs said so, and so did each one whose last instance
        died less than its grace ago (:meth:`held_until_ns`), which may yet come back. Whichever of a
        service's instances said it counts: the one serving the stream, or its earlier self."""
        awaited = {c.name for c in self.registry.with_inputs()}
        now_ns = self._clock_ns()
        awaited |= {c.name for c in self.registry.departed.values()
                    if (until := self.held_until_ns(c)) is not None and now_ns < until}
        ended = self.streams.finished(awaited)
        for stream_id in ended:
            log.info("event=stream_end stream_id=%s", stream_id)
            self.registry.end_stream(stream_id)
        if ended:
            self._on_assignments_changed()
        closed = [event for stream_id in ended if (event := self.partials.on_stream_end(stream_id, now_ns))]
        return closed + [Outgoing(text=_dumps({"type": "stream_end", "stream_id": stream_id}),
                                  stream_id=stream_id) for stream_id in ended]

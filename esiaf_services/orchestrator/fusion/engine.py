"""Fusion: gathers the results of other types around each anchor result, by capture time.

Each anchor result (of a fusion's ``anchor`` type, payload not ``nothing``) opens a fusion
whose window is the anchor's span. Every result of a ``fuse`` type whose span overlaps the
window at all belongs to it, whether it came before or after the anchor. The fusion is
published (revision 1) as soon as every expected component has covered the window — with
results or ``nothing`` results, contiguously up to the window's end — or when the slowest
pending component's own timeout has passed (its deadline: window end + its timeout, see
latency.py). Components that die or leave are no longer waited for. A result that arrives
after publication and belongs to the window publishes the next revision.

Pure bookkeeping, no sockets, no clock of its own beyond ``clock_ns``: planes/ingest.py stores what
this returns, publishes it, and wakes :meth:`FusionEngine.on_timer` at
:meth:`FusionEngine.next_deadline_ns`.
"""
from __future__ import annotations

import heapq
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, cast

from ..settings import FusionSettings, TimeoutSettings
from .aggregate import aggregates, overlaps, ssl_aggregate
from .coverage import Coverage, SpanIndex, StoredResult
from .latency import Latencies
from .models import Completion, FusedResult, Missing, MissingReason, bounded_lists
from .playback import ECHO, PLAYBACK, SPEECH_START, Played, is_robot, overlap_share, played, playing_at

__all__ = ["Fusion", "FusionEngine", "Publication", "StoredResult"]

EVENTS = (PLAYBACK, SPEECH_START, ECHO)  # kinds that report no coverage of the audio (fusion/playback.py)
PRUNE_EVERY = 64  # results per stream between two prunings of its memory
MAX_REPLAYED_STREAMS = 10_000  # replayed streams remembered (whose latencies are not learnt)
COMPLETE, TIMED_OUT, COMPONENTS_GONE = "complete", "timed_out", "components_gone"


class LiveComponent(Protocol):
    name: str
    kind: str  # the result kind it produces
    stream_id: str


@dataclass(frozen=True)
class Publication:
    """A fused result to store and publish, and when it was due."""

    result: FusedResult
    start_ns: int  # the anchor's span
    end_ns: int
    trigger_received_ns: int | None = None  # the result that completed it, if one did
    due_ns: int | None = None  # the deadline it was published at, if its timer published it
    withdraws: bool = False  # the robot's voice, and its previous revision was sent as a person's

    @property
    def id(self) -> int:
        return self.result.id

    @property
    def revision(self) -> int:
        return self.result.revision

    @property
    def fusion(self) -> str:
        return self.result.fusion

    @property
    def stream_id(self) -> str:
        return self.result.stream_id

    @property
    def published_ns(self) -> int:
        return self.result.published_ns


@dataclass
class Fusion:
    """One anchor's fusion, open (revision 0) or published."""

    settings: FusionSettings
    id: int
    anchor: StoredResult
    results: dict[str, dict[int, StoredResult]]
    waiting: dict[str, tuple[str, int]]  # component -> (type, deadline_ns)
    missing: dict[str, tuple[str, str]] = field(default_factory=dict)  # -> (type, reason)
    revision: int = 0
    completion: str = ""
    scheduled_ns: int | None = None  # the deadline of its one valid timer-heap entry
    published_ns: int = 0  # when its latest revision was published
    revision_due_ns: int | None = None  # a coalesced revision waits for this time
    # an orphan's (orphans.py): the service whose anchor it stands in for; that anchor, if it comes after
    # all, takes its place (_adopt) instead of opening a second fusion over the same utterance
    stand_in_for: str | None = None
    person_shown: bool = False  # its latest revision was published as a person's (clients without the robot have it)

    @property
    def window(self) -> tuple[int, int]:
        return self.anchor.start_ns, self.anchor.end_ns

    @property
    def start_ns(self) -> int:  # start_ns, end_ns, id: published fusions live in a SpanIndex
        return self.anchor.start_ns

    @property
    def end_ns(self) -> int:
        return self.anchor.end_ns

    def deadline_ns(self) -> int:
        """When it must be published: the latest deadline of a pending component (0: now)."""
        return max((deadline for _, deadline in self.waiting.values()), default=0)

    def add(self, result: StoredResult) -> bool:
        """Includes ``result`` if it belongs to the window and is new; says whether it did."""
        by_id = self.results.get(result.type)
        if by_id is None or result.id in by_id or result.is_nothing:
            return False
        if not overlaps(result.start_ns, result.end_ns, *self.window):
            return False
        by_id[result.id] = result
        return True


@dataclass
class StreamMemory:
    coverage: dict[str, Coverage] = field(default_factory=dict)  # by component
    index: dict[str, SpanIndex] = field(default_factory=dict)  # real results, by type
    ended: set[str] = field(default_factory=set)  # components that said end_of_stream since
    open: list[Fusion] = field(default_factory=list)
    published: SpanIndex = field(default_factory=SpanIndex)  # by window, for late results
    newest_end_ns: int = 0
    answered: dict[str, int] = field(default_factory=dict)  # by component: the end of its latest result
    since_prune: int = 0


@dataclass
class Changes:
    """What the store must record besides the fused results (ingest drains it per commit)."""

    opened: list[tuple[Fusion, int]] = field(default_factory=list)  # (fusion, received_ns)
    closed: list[int] = field(default_factory=list)  # fused ids no longer pending


class FusionEngine:
    def __init__(self, fusions: Iterable[FusionSettings], allocate_id: Callable[[], int],
                 live_components: Callable[[], Iterable[LiveComponent]] = lambda: (),
                 timeouts: TimeoutSettings | None = None,
                 clock_ns: Callable[[], int] = time.time_ns,
                 capture_offset_ns: Callable[[str], int] = lambda stream_id: 0,
                 out_of_set_is_nothing: bool = False) -> None:
        self._allocate_id = allocate_id
        self.out_of_set_is_nothing = out_of_set_is_nothing  # fusion/playback.py is_robot's
        # a stream's capture times are on its capturing host's clock: this much added puts them on ours
        self._capture_offset_ns = capture_offset_ns
        self._live = live_components
        self._clock_ns = clock_ns
        self.timeouts = timeouts or TimeoutSettings()
        self.memory_ns = int(self.timeouts.memory_s * 1e9)
        self.latencies = Latencies(self.timeouts)
        # streams played faster than real time (a file replayed with --fast): their capture times run
        # ahead of the clock, so their latencies say nothing of a real-time run's and are not learnt
        self.replayed: OrderedDict[str, None] = OrderedDict()
        self.streams: dict[str, StreamMemory] = {}
        self.open: dict[int, Fusion] = {}  # by fused id
        self.changes = Changes()
        self._heap: list[tuple[int, int]] = []  # (deadline_ns, fused id)
        self._revisions: list[tuple[int, int]] = []  # (due_ns, fused id) of coalesced revisions
        self._revising: dict[int, Fusion] = {}
        self._revision_interval_ns = int(self.timeouts.revision_interval_s * 1e9)
        self.fusions: list[FusionSettings] = []
        self.replace_fusions(fusions)

    def replace_fusions(self, fusions: Iterable[FusionSettings]) -> None:
        """New configuration for anchors from now on; open fusions finish under their own."""
        self.fusions = list(fusions)
        self._by_anchor: dict[str, list[FusionSettings]] = {}
        for fusion in self.fusions:
            self._by_anchor.setdefault(fusion.anchor, []).append(fusion)

    def mark_replayed(self, stream_id: str) -> None:
        """``stream_id`` is played faster than real time: its latencies are not learnt."""
        self.replayed[stream_id] = None
        self.replayed.move_to_end(stream_id)
        while len(self.replayed) > MAX_REPLAYED_STREAMS:
            self.replayed.popitem(last=False)

    # events
    def on_result(self, result: StoredResult, received_ns: int) -> list[Publication]:
        """Fused results that ``result`` completes or revises, to store and publish in order."""
        latency_ns = received_ns - (result.end_ns + self._capture_offset_ns(result.stream_id))
        if result.stream_id not in self.replayed and latency_ns >= 0:  # < 0: clocks disagree beyond the offset
            self.latencies.add(result.component, latency_ns)
        memory = self._remember(result)
        fused: list[Publication] = []
        if not result.is_nothing:
            for fusion in list(memory.published.overlapping(result.start_ns, result.end_ns)):
                if fusion.add(result):  # late: a new revision, at most one per revision interval
                    fused.extend(self._revise(fusion, received_ns))
            for fusion in memory.open:
                fusion.add(result)
        for fusion in list(memory.open):
            if result.component in fusion.waiting and \
                    memory.coverage[result.component].covers(*fusion.window):
                del fusion.waiting[result.component]
                if not fusion.waiting:
                    fused.append(self._publish(fusion, received_ns))
                else:
                    self._schedule(fusion)
        if not result.is_nothing:
            for settings in self._by_anchor.get(result.type, ()):
                if settings.stream is None or settings.stream == result.stream_id:
                    orphan = self._stood_in(settings, result, memory)
                    fused.extend(self._open(settings, result, memory, received_ns) if orphan is None
                                 else self._adopt(orphan, result, memory, received_ns))
        return fused

    @staticmethod
    def _stood_in(settings: FusionSettings, anchor: StoredResult, memory: StreamMemory) -> Fusion | None:
        """The fusion of ``settings`` that was opened over ``anchor``'s span without it, standing in for
        its service (orphans.py), if any: the one that overlaps it most."""
        span = anchor.start_ns, anchor.end_ns
        found = [f for f in [*memory.published.overlapping(*span), *memory.open]
                 if f.settings.name == settings.name and f.stand_in_for == anchor.component
                 and overlaps(f.start_ns, f.end_ns, *span)]
        return max(found, key=lambda f: min(f.end_ns, span[1]) - max(f.start_ns, span[0]), default=None)

    def _adopt(self, fusion: Fusion, anchor: StoredResult, memory: StreamMemory,
               received_ns: int) -> list[Publication]:
        """``anchor`` came after all for an utterance fused without it: it becomes that fusion's anchor
        (the results of its window with it) and its service is no longer missing; a published fusion's
        next revision says so. One fused result per utterance, never two."""
        published = fusion.revision > 0
        if published:
            memory.published.remove(fusion)  # filed by its window, which may change
        before = fusion.results
        fusion.anchor, fusion.stand_in_for = anchor, None
        fusion.missing.pop(anchor.component, None)
        fusion.results = self._new_fusion(fusion.settings, fusion.id, anchor, memory).results
        for type_name, by_id in before.items():  # what the memory may have forgotten since
            fusion.results.setdefault(type_name, {}).update(
                {i: r for i, r in by_id.items() if overlaps(r.start_ns, r.end_ns, *fusion.window)})
        if not published:
            return []  # published once complete, as any open fusion
        memory.published.add(fusion)
        return self._revise(fusion, received_ns)

    def on_component_gone(self, component: str) -> list[Publication]:
        """A component died or left: no fusion waits for it any longer."""
        fused = []
        for fusion in list(self.open.values()):
            if component in fusion.waiting:
                type_name, _ = fusion.waiting.pop(component)
                fusion.missing[component] = (type_name, "gone")
                if not fusion.waiting:
                    fused.append(self._publish(fusion, None))
                else:
                    self._schedule(fusion)
        return fused

    def on_end_of_stream(self, stream_id: str, component: str) -> list[Publication]:
        """``component`` has sent every result it will for the stream: no fusion of the stream
        waits for it (until it sends for the stream again)."""
        memory = self._memory(stream_id)
        memory.ended.add(component)
        fused = []
        for fusion in list(memory.open):
            if fusion.waiting.pop(component, None) is not None:
                if not fusion.waiting:
                    fused.append(self._publish(fusion, None))
                else:
                    self._schedule(fusion)
        return fused

    def on_timer(self, now_ns: int | None = None) -> list[Publication]:
        """Publishes every fusion whose deadline has passed."""
        now_ns = self._clock_ns() if now_ns is None else now_ns
        fused = []
        while self._revisions and self._revisions[0][0] <= now_ns:
            _due, fused_id = heapq.heappop(self._revisions)
            fusion = self._revising.pop(fused_id, None)
            if fusion is not None:
                fusion.revision_due_ns = None
                fused.append(self._publish(fusion, None))
        while self._heap and self._heap[0][0] <= now_ns:
            deadline, fused_id = heapq.heappop(self._heap)
            fusion = self.open.get(fused_id)
            if fusion is None or fusion.scheduled_ns != deadline:
                continue  # published already, or rescheduled
            for component, (type_name, _) in fusion.waiting.items():
                fusion.missing[component] = (type_name, TIMED_OUT)
            fusion.waiting.clear()
            fused.append(self._publish(fusion, None, due_ns=deadline))
        return fused

    def next_deadline_ns(self) -> int | None:
        revision_due = self._revisions[0][0] if self._revisions else None
        while self._heap:
            deadline, fused_id = self._heap[0]
            fusion = self.open.get(fused_id)
            if fusion is not None and fusion.scheduled_ns == deadline:
                return deadline if revision_due is None else min(deadline, revision_due)
            heapq.heappop(self._heap)
        return revision_due

    def _revise(self, fusion: Fusion, received_ns: int) -> list[Publication]:
        """A late result joined a published fusion: its next revision now, or (if the last one
        is younger than the revision interval) once, at the end of the interval."""
        if fusion.revision_due_ns is not None:
            return []  # coalesced into the revision already waiting
        due_ns = fusion.published_ns + self._revision_interval_ns
        if received_ns >= due_ns:
            return [self._publish(fusion, received_ns)]
        fusion.revision_due_ns = due_ns
        self._revising[fusion.id] = fusion
        heapq.heappush(self._revisions, (due_ns, fusion.id))
        return []

    def playing_at(self, stream_id: str, capture_ns: int) -> Played | None:
        """What the stream's robot was playing at ``capture_ns`` (its playback results), if anything."""
        index = self._memory(stream_id).index.get(PLAYBACK)
        return None if index is None else playing_at(played(r.json for r in index.overlapping(capture_ns, capture_ns)),
                                                     capture_ns)

    def talker(self, stream_id: str, start_ns: int, end_ns: int) -> dict[str, Any] | None:
        """The ssl aggregate of what the localiser heard within [start_ns, end_ns], if it heard anything."""
        index = self._memory(stream_id).index.get("ssl")
        if index is None:
            return None
        return ssl_aggregate([r.json for r in index.overlapping(start_ns, end_ns)], (start_ns, end_ns))

    # restoring after a restart (results first, then fused results, then open fusions)
    def restore_result(self, result: StoredResult) -> None:
        self._remember(result)

    def restore_published(self, fused: dict[str, Any]) -> None:
        anchor = StoredResult.from_json(fused["anchor"])
        settings = FusionSettings(name=fused["fusion"], anchor=anchor.type,
                                  fuse=list(fused["results"]))
        results = {t: {r["id"]: StoredResult.from_json(r) for r in items}
                   for t, items in fused["results"].items()}
        fusion = Fusion(settings=settings, id=fused["id"], anchor=anchor, results=results,
                        waiting={}, revision=fused["revision"], completion=fused["completion"],
                        missing={m["component"]: (m["type"], m["reason"])
                                 for m in fused.get("missing", [])})
        configured = next((f.anchor for f in self.fusions if f.name == settings.name), anchor.type)
        if configured != anchor.type:  # an orphan: it stands in for its missing anchor's service
            fusion.stand_in_for = next((c for c, (t, _) in fusion.missing.items() if t == configured), None)
        self._memory(anchor.stream_id).published.add(fusion)

    def restore_open(self, fused_id: int, settings: FusionSettings, anchor: StoredResult,
                     waiting: dict[str, tuple[str, int]]) -> None:
        """An anchor's fusion that was pending when the orchestrator stopped: it waits for the
        same components until the same deadlines (published by the next on_timer if due)."""
        memory = self._memory(anchor.stream_id)
        fusion = self._new_fusion(settings, fused_id, anchor, memory)
        fusion.waiting = {c: w for c, w in waiting.items()
                          if not self._covered(memory, c, fusion)}
        memory.open.append(fusion)
        self.open[fused_id] = fusion
        self._schedule(fusion)

    # internals
    def _memory(self, stream_id: str) -> StreamMemory:
        memory = self.streams.get(stream_id)
        if memory is None:
            memory = self.streams[stream_id] = StreamMemory()
        return memory

    def _remember(self, result: StoredResult) -> StreamMemory:
        memory = self._memory(result.stream_id)
        if result.type not in EVENTS:  # a playback or speech start says nothing of the audio analysed
            coverage = memory.coverage.get(result.component)
            if coverage is None:
                coverage = memory.coverage[result.component] = Coverage()
            coverage.add(result.start_ns, result.end_ns)
            memory.answered[result.component] = max(memory.answered.get(result.component, 0), result.end_ns)
            memory.ended.discard(result.component)
        if not result.is_nothing:
            index = memory.index.get(result.type)
            if index is None:
                index = memory.index[result.type] = SpanIndex()
            index.add(result)
        if result.type != PLAYBACK:  # a player reports what it is to play: ahead of capture, far ahead in a replay
            memory.newest_end_ns = max(memory.newest_end_ns, result.end_ns)
        memory.since_prune += 1
        if memory.since_prune >= PRUNE_EVERY:
            self._prune(memory)
        return memory

    def _prune(self, memory: StreamMemory) -> None:
        memory.since_prune = 0
        horizon = memory.newest_end_ns - self.memory_ns
        # what a late fusion looks up (the localiser's directions, the robot's playback, the canceller's echo
        # events, the labellers' results and their coverage) is kept until the slowest component still covering
        # the stream has answered past it: in a replay (--fast) the localiser and the canceller run minutes
        # ahead of the recogniser, whose late utterances found neither their direction nor the robot's
        # playback (playback_overlap 0) in their span; at most twice memory_s behind the newest. Live, the
        # components answer in step and this is memory_s behind the newest
        answered = [end for name, end in memory.answered.items() if name not in memory.ended]
        late = max(memory.newest_end_ns - 2 * self.memory_ns,
                   min([memory.newest_end_ns, *answered]) - self.memory_ns)
        for index in memory.index.values():
            index.forget_before(late)
        for coverage in memory.coverage.values():
            coverage.forget_before(late)
        memory.published.forget_before(horizon)

    @staticmethod
    def _covered(memory: StreamMemory, component: str, fusion: Fusion) -> bool:
        coverage = memory.coverage.get(component)
        return coverage is not None and coverage.covers(*fusion.window)

    def _new_fusion(self, settings: FusionSettings, fused_id: int, anchor: StoredResult,
                    memory: StreamMemory) -> Fusion:
        fusion = Fusion(settings=settings, id=fused_id, anchor=anchor,
                        results={t: {} for t in settings.fuse}, waiting={})
        for type_name in settings.fuse:
            index = memory.index.get(type_name)
            if index is not None:
                for result in index.overlapping(*fusion.window):
                    fusion.results[type_name][result.id] = result
        return fusion

    def open_orphan(self, settings: FusionSettings, anchor: StoredResult, missing: dict[str, tuple[str, str]],
                    received_ns: int, stand_in_for: str | None = None) -> list[Publication]:
        """A fusion on a stand-in ``anchor`` (orphans.py), for the anchor ``stand_in_for``'s service did not give."""
        return self._open(settings, anchor, self._memory(anchor.stream_id), received_ns, missing, stand_in_for)

    def _open(self, settings: FusionSettings, anchor: StoredResult, memory: StreamMemory, received_ns: int,
              missing: dict[str, tuple[str, str]] | None = None, stand_in_for: str | None = None) -> list[Publication]:
        fusion = self._new_fusion(settings, self._allocate_id(), anchor, memory)
        fusion.missing.update(missing or {})
        fusion.stand_in_for = stand_in_for
        if settings.fuse:
            types = set(settings.fuse)
            for component in self._live():
                # every live service of a fused type serves every stream (replicas share them):
                # one that has not covered this stream yet is waited for, never assumed done
                if component.kind in types and component.name not in fusion.waiting \
                        and component.name not in memory.ended \
                        and not self._covered(memory, component.name, fusion):
                    deadline = (anchor.end_ns + self._capture_offset_ns(anchor.stream_id)
                                + self.latencies.timeout_ns(component.name))
                    fusion.waiting[component.name] = (component.kind, deadline)
        if not fusion.waiting:
            return [self._publish(fusion, received_ns)]
        memory.open.append(fusion)
        self.open[fusion.id] = fusion
        self.changes.opened.append((fusion, received_ns))
        self._schedule(fusion)
        return []

    def _schedule(self, fusion: Fusion) -> None:
        deadline = fusion.deadline_ns()
        if deadline != fusion.scheduled_ns:
            fusion.scheduled_ns = deadline
            heapq.heappush(self._heap, (deadline, fusion.id))

    def _publish(self, fusion: Fusion, trigger_received_ns: int | None,
                 due_ns: int | None = None) -> Publication:
        memory = self._memory(fusion.anchor.stream_id)
        if fusion.revision == 0:
            if self.open.pop(fusion.id, None) is not None:
                memory.open.remove(fusion)
                self.changes.closed.append(fusion.id)
            memory.published.add(fusion)
            reasons = {reason for _, reason in fusion.missing.values()}
            fusion.completion = (TIMED_OUT if reasons & {TIMED_OUT, "skipped"} else
                                 COMPONENTS_GONE if reasons else COMPLETE)
        else:  # a revision: components that have covered the window since are not missing
            fusion.missing = {c: m for c, m in fusion.missing.items()
                              if not self._covered(memory, c, fusion)}
        fusion.revision += 1
        published_ns = fusion.published_ns = self._clock_ns()
        window = fusion.window
        results = {t: [r.json for r in sorted(by_id.values(), key=lambda r: (r.start_ns, r.id))]
                   for t, by_id in fusion.results.items()}
        summary = aggregates(results, window)  # from every result, before the lists are bounded
        missing = [Missing.model_construct(component=c, type=t, reason=cast(MissingReason, reason))
                   for c, (t, reason) in sorted(fusion.missing.items())]
        index = memory.index.get(PLAYBACK)
        items = played(r.json for r in index.overlapping(*window)) if index is not None else []
        share = round(overlap_share(items, *window), 4)
        echoes = memory.index.get(ECHO)
        robot = is_robot(share, items, fusion.anchor.json, results, summary.get("ssl"),
                         [r.json for r in echoes.overlapping(*window)] if echoes is not None and share else [],
                         out_of_set_is_nothing=self.out_of_set_is_nothing)
        results, omitted = bounded_lists(results)
        # model_construct: every value is the engine's own (results as the codec checked them on arrival)
        result = FusedResult.model_construct(
            id=fusion.id, revision=fusion.revision, fusion=fusion.settings.name,
            stream_id=fusion.anchor.stream_id, anchor=fusion.anchor.json, results=results,
            aggregates=summary, completion=cast(Completion, fusion.completion),
            missing_components=[m.component for m in missing], missing=missing, published_ns=published_ns,
            omitted=omitted, playback_overlap=share, source="robot" if robot else "person")
        withdraws, fusion.person_shown = robot and fusion.person_shown, not robot
        return Publication(result=result, start_ns=window[0], end_ns=window[1],
                           trigger_received_ns=trigger_received_ns, due_ns=due_ns, withdraws=withdraws)

"""Utterances whose anchor will never come: a recogniser instance died with them in flight, or
passed them by.

A fusion opens on its anchor (a ``speech`` result), so an utterance the dead instance had taken
but not answered would otherwise vanish without a trace. When an instance of an anchor type dies,
each VAD segment on the streams it served that its service has not covered since its last answer
is fused anyway: anchored on the segment itself, with the instance's service missing (reason
``gone``, completion ``components_gone``), so a client sees where speech was and that its text is
lost. The next utterance goes to the instance the stream moved to.

An utterance still going on when the instance died reaches the instance the stream moved to from
its middle, which says ``nothing`` about it ("joined late") rather than a wrong sentence. So the
streams a dead instance served are watched (:class:`Orphans`): an anchor-type ``nothing`` there
over speech that began before the death is fused the same way, anchored on its VAD segment.

A live recogniser can pass an utterance by too: its input lost the audio (a subscriber past its
high-water mark when it cannot keep up), or its process stalled. A recogniser answers the
utterances of a stream in order, so when it answers one, each VAD segment between its previous
answer and this one that it said nothing about was passed by; and when it ends the stream, so was
each one after its last answer. Those are fused the same way, with reason ``skipped`` (completion
``timed_out``: a live component did not answer), instead of vanishing.

A recogniser declared dead for its silence may only have stalled (frozen, or held by a long decode):
it keeps its audio for a while (esiaf/transport.py STALL_MS), registers again and answers its
backlog. Meanwhile each new VAD segment on a stream it served is fused without it at once, while no
instance of its service lives (:meth:`Orphans.on_segment`). Its answers, when they come, take the
stand-in anchors' places: each is the next revision of the fused result over its utterance
(fusion/engine.py ``_adopt``), so an utterance is fused once, never twice.

A vad that dies mid-utterance never sends that utterance's segment, and the recogniser, given the next
utterance by the vad's new instance, says ``nothing`` about what it heard of the broken one
("utterance broken off", esiaf/receiving.py). On the streams a dead vad served, such a ``nothing``
over speech that began before the death is fused, anchored on itself, with the vad missing (reason
``gone``), until an utterance begun after the death: the utterance in flight is reported, not lost
without a word.
"""
from __future__ import annotations

import logging
from collections.abc import Callable

from ..settings import FusionSettings
from .aggregate import overlaps
from .coverage import StoredResult
from .engine import FusionEngine, Publication

log = logging.getLogger(__name__)

SEGMENT_TYPE = "vad"  # the results that say where speech was


def unanswered_segments(engine: FusionEngine, stream_id: str, service: str) -> list[StoredResult]:
    """The segments of ``stream_id`` that ``service`` has not covered since its last result there
    (all of them still remembered, if it never answered on this stream)."""
    memory = engine.streams.get(stream_id)
    segments = memory.index.get(SEGMENT_TYPE) if memory is not None else None
    if memory is None or segments is None:
        return []
    coverage = memory.coverage.get(service)
    since_ns = coverage.ends[-1] if coverage is not None and coverage.ends else 0
    return [segment for segment in segments.overlapping(since_ns, 2**63 - 1)
            if segment.start_ns >= since_ns and not (coverage is not None and coverage.covers(
                segment.start_ns, segment.end_ns))]


def anchored(engine: FusionEngine, anchor_type: str, stream_id: str) -> list[FusionSettings]:
    """The fusions that open on results of ``anchor_type`` in ``stream_id``."""
    return [s for s in engine.fusions if s.anchor == anchor_type and s.stream in (None, stream_id)]


def passed_by(engine: FusionEngine, stream_id: str, service: str, before_ns: int) -> list[StoredResult]:
    """The segments of ``stream_id`` wholly between ``service``'s last answer there and
    ``before_ns``: it has said nothing about them. None if it never answered on the stream (it may
    have joined it late)."""
    memory = engine.streams.get(stream_id)
    segments = memory.index.get(SEGMENT_TYPE) if memory is not None else None
    coverage = memory.coverage.get(service) if memory is not None else None
    if segments is None or coverage is None or not coverage.ends:
        return []
    since_ns = coverage.ends[-1]
    return [segment for segment in segments.overlapping(since_ns, before_ns)
            if segment.start_ns >= since_ns and segment.end_ns <= before_ns]


def fuse_without(engine: FusionEngine, segment: StoredResult, service: str, anchor_type: str,
                 received_ns: int, why: str, reason: str = "gone", missing_type: str = "") -> list[Publication]:
    """Fuses ``segment`` for every fusion anchored on ``anchor_type``, ``service`` missing for
    ``reason`` (as a producer of ``missing_type``; by default of the anchor it stands in for), unless a
    fusion of that name is open or published over it already."""
    memory = engine.streams.get(segment.stream_id)
    span = (segment.start_ns, segment.end_ns)
    taken = {f.settings.name for f in [*memory.published.overlapping(*span),
                                       *(f for f in memory.open if overlaps(f.start_ns, f.end_ns, *span))]} \
        if memory is not None else set()
    fused: list[Publication] = []
    for settings in anchored(engine, anchor_type, segment.stream_id):
        if settings.name not in taken:
            log.warning("event=utterance_orphaned stream_id=%s service=%s start_ns=%d end_ns=%d fusion=%s why=%s",
                        segment.stream_id, service, *span, settings.name, why)
            fused.extend(engine.open_orphan(settings, segment, {service: (missing_type or anchor_type, reason)},
                                            received_ns, stand_in_for=None if missing_type else service))
    return fused


def fuse_orphans(engine: FusionEngine, stream_id: str, service: str, anchor_type: str,
                 received_ns: int) -> list[Publication]:
    """Fuses each segment of ``stream_id`` that the dead instance of ``service`` (producing
    ``anchor_type``) left unanswered (:func:`fuse_without`)."""
    if not anchored(engine, anchor_type, stream_id):
        return []
    return [f for segment in unanswered_segments(engine, stream_id, service)
            for f in fuse_without(engine, segment, service, anchor_type, received_ns, "unanswered")]


def fuse_passed_by(engine: FusionEngine, stream_id: str, service: str, anchor_type: str, before_ns: int,
                   received_ns: int) -> list[Publication]:
    """Fuses each segment ``service`` (producing ``anchor_type``) passed by on ``stream_id`` before
    ``before_ns`` (:func:`passed_by`), without it, reason ``skipped``."""
    if not anchored(engine, anchor_type, stream_id):
        return []
    return [f for segment in passed_by(engine, stream_id, service, before_ns)
            for f in fuse_without(engine, segment, service, anchor_type, received_ns, "skipped", reason="skipped")]


class Orphans:
    """What dead instances left: fused at their death (:func:`fuse_orphans`), and the utterances that
    were going on then, once their new instance has said ``nothing`` about them. What live ones
    passed by: fused when they answer a later utterance or end the stream (:func:`fuse_passed_by`)."""

    MAX_WATCHED = 10_000  # (stream, service) pairs watched at once, the oldest dropped; streams of dead vads too

    def __init__(self, engine: FusionEngine) -> None:
        self.engine = engine
        # (stream, service) -> (anchor type, the capture time before which speech was in flight on the dead one)
        self.watched: dict[tuple[str, str], tuple[str, int]] = {}
        # stream -> (the service of a vad that died serving it, the capture time of its death)
        self.segmenters_gone: dict[str, tuple[str, int]] = {}

    def on_death(self, stream_id: str, service: str, anchor_type: str, in_flight_before_ns: int,
                 received_ns: int) -> list[Publication]:
        """An instance of ``service`` (producing ``anchor_type``) died serving ``stream_id``."""
        if anchor_type == SEGMENT_TYPE:  # a vad: the utterance in flight is reported when broken off
            self.segmenters_gone.pop(stream_id, None)
            self.segmenters_gone[stream_id] = (service, in_flight_before_ns)
            while len(self.segmenters_gone) > self.MAX_WATCHED:
                del self.segmenters_gone[next(iter(self.segmenters_gone))]
            return []
        if not anchored(self.engine, anchor_type, stream_id):
            return []
        self.watched.pop((stream_id, service), None)
        self.watched[stream_id, service] = (anchor_type, in_flight_before_ns)
        while len(self.watched) > self.MAX_WATCHED:
            del self.watched[next(iter(self.watched))]
        return fuse_orphans(self.engine, stream_id, service, anchor_type, received_ns)

    def on_segment(self, segment: StoredResult, received_ns: int, alive: Callable[[str], bool]) -> list[Publication]:
        """A VAD segment arrived: on a stream whose recogniser died, while no instance of its service is
        ``alive``, nobody will answer it now; fused without it at once (its answer, if it comes back and
        gives one, revises that)."""
        if segment.type != SEGMENT_TYPE or segment.is_nothing:
            return []
        return [f for (stream_id, service), (anchor_type, _) in list(self.watched.items())
                if stream_id == segment.stream_id and not alive(service)
                for f in fuse_without(self.engine, segment, service, anchor_type, received_ns, "no_live_instance")]

    def before_result(self, result: StoredResult, received_ns: int) -> list[Publication]:
        """``result`` is about to be fused: the segments its service passed by before it."""
        return fuse_passed_by(self.engine, result.stream_id, result.component, result.type, result.start_ns,
                              received_ns)

    def on_end_of_stream(self, stream_id: str, service: str, anchor_type: str,
                         received_ns: int) -> list[Publication]:
        """``service`` sent its last result for the stream: the segments it passed by after its last answer."""
        return fuse_passed_by(self.engine, stream_id, service, anchor_type, 2**63 - 1, received_ns)

    def on_result(self, result: StoredResult, received_ns: int) -> list[Publication]:
        """``result`` just fused: if it is its new instance's ``nothing`` over an utterance that was
        in flight on a dead one, that utterance's segment is fused without it; if it is a ``nothing``
        over an utterance a dead vad broke off, that utterance is fused as lost."""
        return self._broken_off(result, received_ns) + self._joined_late(result, received_ns)

    def _broken_off(self, result: StoredResult, received_ns: int) -> list[Publication]:
        gone = self.segmenters_gone.get(result.stream_id)
        if gone is None or not anchored(self.engine, result.type, result.stream_id):
            return []
        service, died_ns = gone
        if result.start_ns >= died_ns:  # an utterance begun after the vad's death: the watch is over
            del self.segmenters_gone[result.stream_id]
            return []
        if not result.is_nothing:
            return []
        return fuse_without(self.engine, result, service, result.type, received_ns, "vad_died",
                            missing_type=SEGMENT_TYPE)

    def _joined_late(self, result: StoredResult, received_ns: int) -> list[Publication]:
        watch = self.watched.get((result.stream_id, result.component))
        if watch is None or result.type != watch[0]:
            return []
        if result.start_ns >= watch[1]:  # an utterance begun after the death: the watch is over
            del self.watched[result.stream_id, result.component]
            return []
        if not result.is_nothing:
            return []
        memory = self.engine.streams.get(result.stream_id)
        segments = memory.index.get(SEGMENT_TYPE) if memory is not None else None
        # on its VAD segment; if that has not come yet (the two are sent at the same moment), on the `nothing`
        anchors = (list(segments.overlapping(result.start_ns, result.end_ns)) if segments else []) or [result]
        return [f for segment in anchors
                for f in fuse_without(self.engine, segment, result.component, watch[0], received_ns, "joined_late")]

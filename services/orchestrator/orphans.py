"""Utterances whose anchor will never come: a recogniser instance died with them in flight.

A fusion opens on its anchor (a ``speech`` result), so an utterance the dead instance had taken
but not answered would otherwise vanish without a trace. When an instance of an anchor type dies,
each VAD segment on the streams it served that its service has not covered since its last answer
is fused anyway: anchored on the segment itself, with the instance's service missing (reason
``gone``, completion ``components_gone``), so a client sees where speech was and that its text is
lost. The next utterance goes to the instance the stream moved to.
"""
from __future__ import annotations

import logging

from .aggregate import overlaps
from .coverage import StoredResult
from .fusion import FusedResult, FusionEngine

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


def fuse_orphans(engine: FusionEngine, stream_id: str, service: str, anchor_type: str,
                 received_ns: int) -> list[FusedResult]:
    """Fuses each segment of ``stream_id`` that the dead instance of ``service`` (producing
    ``anchor_type``) left unanswered, for every fusion anchored on that type, unless a fusion of
    that name is open or published over it already."""
    fusions = [s for s in engine.fusions if s.anchor == anchor_type and s.stream in (None, stream_id)]
    if not fusions:
        return []
    memory = engine.streams.get(stream_id)
    fused: list[FusedResult] = []
    for segment in unanswered_segments(engine, stream_id, service):
        assert memory is not None  # there are segments
        for settings in fusions:
            span = (segment.start_ns, segment.end_ns)
            fusions_over = [*memory.published.overlapping(*span),
                            *(f for f in memory.open if overlaps(f.start_ns, f.end_ns, *span))]
            if any(f.settings.name == settings.name for f in fusions_over):
                continue
            log.warning("event=utterance_orphaned stream_id=%s service=%s start_ns=%d end_ns=%d fusion=%s",
                        stream_id, service, segment.start_ns, segment.end_ns, settings.name)
            fused.extend(engine.open_orphan(settings, segment, {service: (anchor_type, "gone")}, received_ns))
    return fused

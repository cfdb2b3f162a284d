"""What the robot played, per stream: the capture spans of a player's audio that sound.

A player publishes every chunk it sends to the loudspeaker (``player/audio``), stamped in the
capture clock. An analyser that subscribes to that topic as a second input
(:meth:`esiaf.UtteranceAnalyser.listen_to_playback`) hands each chunk to :class:`PlayedSpans`, which
keeps the spans of the chunks whose level reaches ``silent_dbfs`` (a recorded robot voice's long
silences are not playing), adjoining ones merged, the newest ``keep`` per stream; and answers
whether an utterance's capture span overlapped them, with ``tail_ms`` after each (the echo's delay
and the room's reverberation reach the microphones after the chunk's stamp).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from esiaf.audio import Audio
from esiaf.per_stream import PerStream

SILENT_DBFS = -50.0  # a chunk quieter than this (RMS, dB re full scale) is not playing: the player's own limit
BRIDGE_NS = 100_000_000  # spans this close merge into one
MS = 1_000_000


class PlayedSpans:
    """The spans a player played, per stream (at most ``max_streams`` streams, ``keep`` spans each)."""

    def __init__(self, keep: int = 256, tail_ms: float = 300.0, silent_dbfs: float = SILENT_DBFS,
                 max_streams: int = 256, info: dict[str, Any] | None = None):
        if keep < 1:
            raise ValueError(f"keep must be at least 1, not {keep}")
        self.tail_ns, self.silent_dbfs = int(tail_ms * MS), silent_dbfs
        self.spans: PerStream[deque[list[int]]] = PerStream(lambda _: deque(maxlen=keep), max_streams,
                                                             "played spans", info=info)

    def add(self, audio: Audio) -> None:
        """A chunk the player published: kept if it sounds."""
        if not audio.frames:
            return
        samples = audio.as_float().astype(np.float64)
        rms = math.sqrt(float(np.mean(np.square(samples))))
        if rms <= 0 or 20 * math.log10(rms) < self.silent_dbfs:
            return
        self.add_span(audio.stream_id, audio.start_ns, audio.end_ns)

    def add_span(self, stream_id: str, start_ns: int, end_ns: int) -> None:
        spans = self.spans.get(stream_id)
        if spans and start_ns <= spans[-1][1] + BRIDGE_NS and end_ns >= spans[-1][0]:
            spans[-1][0], spans[-1][1] = min(spans[-1][0], start_ns), max(spans[-1][1], end_ns)
        else:
            spans.append([start_ns, end_ns])

    def overlaps(self, stream_id: str, start_ns: int, end_ns: int) -> bool:
        """Whether the capture span [start_ns, end_ns) overlapped anything played on the stream, or its
        ``tail_ms`` after."""
        if stream_id not in self.spans:
            return False
        return any(start_ns < played_end + self.tail_ns and played_start < end_ns
                   for played_start, played_end in self.spans[stream_id])

    def __contains__(self, stream_id: str) -> bool:
        return stream_id in self.spans

"""The original ESIAF double-threshold segmenter, timed by capture time.

Level of a chunk = 96 + 20·log10(peak), the peak relative to full scale (so a
full-scale chunk is 96 dB, the dynamic range of 16-bit audio). A segment
starts on a chunk louder than ``db_min``, stays alive while chunks are louder
than ``db_keep_alive``, and ends on the first chunk that ends
``keep_alive_ms`` after the last loud one, or when it has lasted ``max_ms``.
Every duration is measured on the chunks' capture timestamps, never on the
wall clock, so the segmentation of a file is the same at any playback speed.

Only speech is forwarded: the ``pre_roll_ms`` of audio before the onset (so
onsets are not clipped), the segment, and the hangover before its end; the
last forwarded chunk is marked ended. The segment's speech span runs from the
start of the onset chunk to the end of the last loud chunk.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")

MS_NS = 1_000_000


def level_db(peak: float) -> float:
    """96 + 20·log10(peak); -inf for digital silence."""
    return 96.0 + 20.0 * math.log10(peak) if peak > 0 else -math.inf


@dataclass(frozen=True)
class SegmenterParams:
    db_min: float = 65.0
    db_keep_alive: float = 60.0
    keep_alive_ms: float = 400.0
    max_ms: float = 8000.0
    pre_roll_ms: float = 250.0

    def __post_init__(self) -> None:
        if self.db_keep_alive > self.db_min:
            raise ValueError(f"db_keep_alive ({self.db_keep_alive}) must not exceed db_min ({self.db_min})")
        for name in ("keep_alive_ms", "max_ms", "pre_roll_ms"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative")


@dataclass(frozen=True)
class Forward(Generic[T]):
    """Forward ``item``; if ``ended``, it is the segment's last chunk and ``segment`` its speech span."""

    item: T
    ended: bool = False
    segment: tuple[int, int] | None = None


class Segmenter(Generic[T]):
    def __init__(self, params: SegmenterParams = SegmenterParams()):
        self.params = params
        self._pre_roll: deque[tuple[T, int, int]] = deque()
        self._speech_start_ns: int | None = None
        self._last_loud_end_ns = 0

    @property
    def active(self) -> bool:
        return self._speech_start_ns is not None

    def process(self, item: T, start_ns: int, end_ns: int, level: float, *,
                force_end: bool = False) -> list[Forward[T]]:
        """One chunk in, what to forward out. ``force_end`` closes an open segment on this chunk."""
        p = self.params
        if not self.active:
            if level <= p.db_min:
                self._remember(item, start_ns, end_ns)
                return []
            self._speech_start_ns = start_ns
            self._last_loud_end_ns = end_ns
            out = [Forward(chunk) for chunk, _, _ in self._pre_roll]
            self._pre_roll.clear()
            if force_end:
                return out + [self._end(item, end_ns)]
            return out + [Forward(item)]
        if level > p.db_keep_alive:
            self._last_loud_end_ns = end_ns
        quiet_ns = end_ns - self._last_loud_end_ns
        if force_end or quiet_ns >= p.keep_alive_ms * MS_NS:
            return [self._end(item, self._last_loud_end_ns)]
        if end_ns - self._speech_start_ns >= p.max_ms * MS_NS:
            return [self._end(item, self._last_loud_end_ns)]
        return [Forward(item)]

    def _end(self, item: T, speech_end_ns: int) -> Forward[T]:
        segment = (self._speech_start_ns, speech_end_ns)
        self._speech_start_ns = None
        return Forward(item, ended=True, segment=segment)

    def _remember(self, item: T, start_ns: int, end_ns: int) -> None:
        self._pre_roll.append((item, start_ns, end_ns))
        while self._pre_roll and end_ns - self._pre_roll[0][2] >= self.params.pre_roll_ms * MS_NS:
            self._pre_roll.popleft()

"""Segmenters timed by capture time: ESIAF's original double-threshold one, and one on speech probabilities.

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
    probability: float = 1.0  # the segment's mean speech probability (1 where the segmenter has none)


class Segmenter(Generic[T]):
    def __init__(self, params: SegmenterParams = SegmenterParams()):
        self.params = params
        self._pre_roll: deque[tuple[T, int, int]] = deque()
        self._speech_start_ns: int | None = None
        self._last_loud_end_ns = 0

    @property
    def active(self) -> bool:
        return self._speech_start_ns is not None

    @property
    def speech_start_ns(self) -> int | None:
        """The open segment's speech start, if one is open."""
        return self._speech_start_ns

    @property
    def speech_heard(self) -> tuple[int, int] | None:
        """Speech begun and not ended: (its start, how long of it has been heard, ns), if any."""
        start = self._speech_start_ns
        return None if start is None else (start, self._last_loud_end_ns - start)

    def process(self, item: T, start_ns: int, end_ns: int, level: float, *,
                force_end: bool = False) -> list[Forward[T]]:
        """One chunk in, what to forward out. ``force_end`` closes an open segment on this chunk."""
        p = self.params
        if self._speech_start_ns is None:  # not active
            if level <= p.db_min:
                self._remember(item, start_ns, end_ns)
                return []
            self._speech_start_ns = start_ns
            self._last_loud_end_ns = end_ns
            out = [Forward(chunk) for chunk, _, _ in self._pre_roll]
            self._pre_roll.clear()
            if force_end:
                return [*out, self._end(item, end_ns)]
            return [*out, Forward(item)]
        if level > p.db_keep_alive:
            self._last_loud_end_ns = end_ns
        quiet_ns = end_ns - self._last_loud_end_ns
        if force_end or quiet_ns >= p.keep_alive_ms * MS_NS:
            return [self._end(item, self._last_loud_end_ns)]
        if end_ns - self._speech_start_ns >= p.max_ms * MS_NS:
            return [self._end(item, self._last_loud_end_ns)]
        return [Forward(item)]

    def _end(self, item: T, speech_end_ns: int) -> Forward[T]:
        assert self._speech_start_ns is not None  # it ends an open segment
        segment = (self._speech_start_ns, speech_end_ns)
        self._speech_start_ns = None
        return Forward(item, ended=True, segment=segment)

    def _remember(self, item: T, start_ns: int, end_ns: int) -> None:
        self._pre_roll.append((item, start_ns, end_ns))
        while self._pre_roll and end_ns - self._pre_roll[0][2] >= self.params.pre_roll_ms * MS_NS:
            self._pre_roll.popleft()


@dataclass(frozen=True)
class ProbabilityParams:
    threshold: float = 0.5  # a chunk this speech-like starts speech
    threshold_off: float = 0.35  # speech goes on while chunks are at least this speech-like (hysteresis)
    min_speech_ms: float = 250.0  # shorter bursts are not speech (held back until this much is heard)
    min_silence_ms: float = 400.0  # a segment ends after this long below threshold_off
    max_ms: float = 8000.0
    pre_roll_ms: float = 250.0
    cut_search_ms: float = 2000.0  # a segment at max_ms is cut at its least speech-like chunk this far back
    onset_pad_ms: float = 100.0  # the speech span starts this long before the first speech-like chunk

    def __post_init__(self) -> None:
        if not 0 < self.threshold <= 1:
            raise ValueError(f"threshold must be in (0, 1], not {self.threshold}")
        if not 0 <= self.threshold_off <= self.threshold:
            raise ValueError(f"threshold_off ({self.threshold_off}) must be in [0, threshold ({self.threshold})]")
        for name in ("min_speech_ms", "min_silence_ms", "max_ms", "pre_roll_ms", "cut_search_ms", "onset_pad_ms"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative")
        if self.max_ms and self.cut_search_ms >= self.max_ms:
            raise ValueError(f"cut_search_ms ({self.cut_search_ms:g}) must be shorter than max_ms ({self.max_ms:g})")


@dataclass
class _Chunk(Generic[T]):
    item: T
    start_ns: int
    end_ns: int
    probability: float


class ProbabilitySegmenter(Generic[T]):
    """Segments chunks by their speech probability (a neural VAD's), timed by capture time.

    Speech starts on a chunk at least ``threshold`` speech-like and is confirmed once it has gone on
    (above ``threshold_off``) for ``min_speech_ms``: until then its chunks are held back, and a
    shorter burst is dropped into the pre-roll. A segment ends ``min_silence_ms`` after its last
    chunk above ``threshold_off``. A segment that reaches ``max_ms`` is cut at its least speech-like
    chunk within the last ``cut_search_ms`` (held back from then on), so a long stretch of speech is
    split in a pause rather than mid-word; what follows the cut starts the next segment. The speech
    span starts ``onset_pad_ms`` before the first speech-like chunk (within the pre-roll), since the
    probability rises a window or so after a soft onset.
    The ended chunk carries the segment's speech span and its mean speech probability."""

    def __init__(self, params: ProbabilityParams = ProbabilityParams()):
        self.params = params
        self._pre_roll: deque[_Chunk[T]] = deque()
        self._candidate: list[_Chunk[T]] = []  # speech started, not yet confirmed
        self._held: list[_Chunk[T]] = []  # confirmed, held back for a cut at max_ms
        self._start_ns: int | None = None  # of the confirmed segment's speech
        self._last_speech_end_ns = 0
        self._probabilities: list[tuple[int, float]] = []  # (end, probability) of the segment's speech chunks

    @property
    def active(self) -> bool:
        return self._start_ns is not None

    @property
    def speech_start_ns(self) -> int | None:
        """The open (confirmed) segment's speech start, if one is open."""
        return self._start_ns

    @property
    def speech_heard(self) -> tuple[int, int] | None:
        """Speech begun and not ended or dropped, confirmed as a segment or not yet: (the start of its first
        window above ``threshold``, how long from there to its last window above ``threshold_off``, ns)."""
        if self._start_ns is not None:
            return self._start_ns, self._last_speech_end_ns - self._start_ns
        if self._candidate:
            onset = self._candidate[0].start_ns
            return onset, self._last_speech_end_ns - onset
        return None

    def process(self, item: T, start_ns: int, end_ns: int, probability: float, *,
                force_end: bool = False) -> list[Forward[T]]:
        """One chunk and its speech probability in, what to forward out."""
        chunk = _Chunk(item, start_ns, end_ns, probability)
        p = self.params
        if self._start_ns is None:
            return self._idle(chunk, force_end)
        if probability >= p.threshold_off:
            self._last_speech_end_ns = end_ns
            self._probabilities.append((end_ns, probability))
        ended = force_end or end_ns - self._last_speech_end_ns >= p.min_silence_ms * MS_NS
        if not ended and p.max_ms and end_ns - self._start_ns >= (p.max_ms - p.cut_search_ms) * MS_NS:
            self._held.append(chunk)
            if end_ns - self._start_ns >= p.max_ms * MS_NS:
                return self._cut()
            return []
        out = [Forward(c.item) for c in self._held]
        self._held.clear()
        if ended:
            return [*out, self._end(item, self._last_speech_end_ns)]
        return [*out, Forward(item)]

    def _idle(self, chunk: _Chunk[T], force_end: bool) -> list[Forward[T]]:
        p = self.params
        if not self._candidate:
            if chunk.probability < p.threshold:
                self._remember(chunk)
                return []
            self._last_speech_end_ns = chunk.end_ns
        elif chunk.probability >= p.threshold_off:
            self._last_speech_end_ns = chunk.end_ns
        self._candidate.append(chunk)
        onset = self._candidate[0]
        if self._last_speech_end_ns - onset.start_ns >= p.min_speech_ms * MS_NS:
            return self._confirm(force_end)
        if force_end or chunk.end_ns - self._last_speech_end_ns >= p.min_silence_ms * MS_NS:
            for held in self._candidate:  # a burst too short to be speech
                self._remember(held)
            self._candidate.clear()
        return []

    def _confirm(self, force_end: bool) -> list[Forward[T]]:
        onset = self._candidate[0]
        # a neural VAD's probability rises a window or so after a soft onset: the span starts a little
        # earlier, but never before the audio forwarded with it
        earliest = self._pre_roll[0].start_ns if self._pre_roll else onset.start_ns
        self._start_ns = max(earliest, onset.start_ns - int(self.params.onset_pad_ms * MS_NS))
        self._probabilities = [(c.end_ns, c.probability) for c in self._candidate
                               if c.probability >= self.params.threshold_off]
        out = [Forward(c.item) for c in self._pre_roll] + [Forward(c.item) for c in self._candidate[:-1]]
        last = self._candidate[-1]
        self._pre_roll.clear()
        self._candidate = []
        if force_end:
            return [*out, self._end(last.item, self._last_speech_end_ns)]
        return [*out, Forward(last.item)]

    def _cut(self) -> list[Forward[T]]:
        assert self._start_ns is not None  # it cuts an open segment
        held, self._held = self._held, []
        at = min(range(len(held)), key=lambda i: (held[i].probability, -i))
        speech_end_ns = held[at].end_ns if held[at].probability >= self.params.threshold_off else held[at].start_ns
        out = [Forward(c.item) for c in held[:at]] + [self._end(held[at].item, max(speech_end_ns, self._start_ns))]
        for chunk in held[at + 1:]:  # what follows the cut starts afresh
            out += self.process(chunk.item, chunk.start_ns, chunk.end_ns, chunk.probability)
        return out

    def _end(self, item: T, speech_end_ns: int) -> Forward[T]:
        assert self._start_ns is not None  # it ends an open segment
        segment = (self._start_ns, speech_end_ns)
        within = [p for end_ns, p in self._probabilities if end_ns <= speech_end_ns]
        probability = sum(within) / len(within) if within else 0.0
        self._start_ns, self._probabilities = None, []
        return Forward(item, ended=True, segment=segment, probability=probability)

    def _remember(self, chunk: _Chunk[T]) -> None:
        self._pre_roll.append(chunk)
        while self._pre_roll and chunk.end_ns - self._pre_roll[0].end_ns >= self.params.pre_roll_ms * MS_NS:
            self._pre_roll.popleft()

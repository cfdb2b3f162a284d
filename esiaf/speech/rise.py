"""A new talker within a stretch of speech: a sharp rise of the speech probability after a plateau.

The vad announces ``speech_start`` once per stretch of speech. Over babble (or the robot's residual
echo) a stretch can already be open, and announced, when a person starts speaking: their onset gets
no event of its own. Silero's probability shows it as a jump from a plateau (babble: a mean of 0.3-0.55)
to confident speech (0.75-0.95) within a window or two. :class:`Rise` finds such a jump: a window at
least ``to`` after a plateau of ``plateau_ms`` (the ``ramp_ms`` just before the window left out, the
rise itself) whose mean is at most ``from_`` and at least ``by`` below the window; the rise's onset is
the first window of the ramp above the plateau by ``by / 2``, else the window itself.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

MS_NS = 1_000_000


@dataclass(frozen=True)
class RiseParams:
    to: float = 0.75  # a window at least this speech-like ...
    from_: float = 0.55  # ... after a plateau whose mean probability is at most this ...
    by: float = 0.25  # ... and at least this much below the window
    plateau_ms: float = 256.0  # the plateau: this long, before the ramp
    ramp_ms: float = 64.0  # the rise itself: left out of the plateau

    def __post_init__(self) -> None:
        if not 0 < self.to <= 1 or not 0 <= self.from_ <= 1 or not 0 < self.by <= 1:
            raise ValueError(f"rise probabilities must be in [0, 1] (to {self.to}, from {self.from_}, by {self.by})")
        if self.plateau_ms <= 0 or self.ramp_ms < 0:
            raise ValueError(f"rise plateau_ms must be positive and ramp_ms not negative "
                             f"({self.plateau_ms}, {self.ramp_ms})")


class Rise:
    """Feed it every window (or chunk) and its probability; it says when one ends a sharp rise."""

    def __init__(self, params: RiseParams = RiseParams()):
        self.params = params
        self._windows: deque[tuple[int, int, float]] = deque()  # (start, end, probability), oldest first
        self._first_ns: int | None = None  # the first window's start: a plateau needs that much heard

    def window(self, start_ns: int, end_ns: int, probability: float) -> int | None:
        """This window's probability in; the onset of the rise it ends (ns), or None."""
        p = self.params
        keep_ns = (p.plateau_ms + p.ramp_ms) * MS_NS
        past = self._windows
        past.append((start_ns, end_ns, probability))
        while start_ns - past[0][0] > keep_ns:
            past.popleft()
        if self._first_ns is None:
            self._first_ns = start_ns
        if probability < p.to or start_ns - self._first_ns < keep_ns:  # not high, or too little heard yet
            return None
        ramp_from = start_ns - p.ramp_ms * MS_NS
        plateau = [q for s, _, q in past if s < ramp_from]
        if not plateau:
            return None
        level = sum(plateau) / len(plateau)
        if level > p.from_ or probability - level < p.by:
            return None
        ramp = [(s, q) for s, _, q in past if ramp_from <= s < start_ns and q > level + p.by / 2]
        return ramp[0][0] if ramp else start_ns

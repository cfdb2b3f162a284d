"""The robot's own loudspeaker direction, learnt from where sound comes from while its player plays.

The player publishes what it sends to the loudspeaker (``player/audio``, stamped in the capture clock
with the time it is played). Its echo reaches the microphones 0 to ``max_delay_ms`` later, so a frame
``[start, end]`` holds the robot's voice when the reference was loud (in chunks above ``LOUD_DBFS``)
over at least half of ``[start - max_delay, end]`` (speech has short pauses), and holds none of it
when the reference was quiet over all of it (frames in between tell nothing and are not counted).
The directions found in each kind of frame go into two histograms of azimuth (1° bins, each frame
counted once in each bin within ``width / 4`` of one of its directions). The robot is where directions
are much more often found while it plays than while it does not (people talk in both; its loudspeaker
only in the first):

    score(az) = share of playing frames with a direction within width / 4 of az
              - the same share of quiet frames

and the direction is known once ``min_frames`` playing frames had directions, the peak's share of them
is at least ``min_share`` and its score at least ``min_lead``. The estimate is the mean (circular) of
the playing frames' directions around the peak, and is kept up to date as frames come.

A frame's reference may arrive after it (the player and the microphones are separate processes): frames
wait until the reference covers them, or for ``wait_s`` of later frames (then, no player: quiet).
Pure: no I/O.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

NS = 1_000_000_000
LOUD_DBFS = -50.0  # a reference chunk this loud (RMS, full scale 0 dB) plays
PLAYING_SHARE = 0.5  # of the reach of a frame's echo: the robot's speech has pauses between words


@dataclass
class _Pending:
    start_ns: int
    end_ns: int
    azimuths: list[float]


class SelfDirection:
    """One stream's estimate of the robot's own direction."""

    def __init__(self, width_deg: float = 40.0, max_delay_ms: float = 400.0, min_frames: int = 20,
                 min_share: float = 0.3, min_lead: float = 0.2, wait_s: float = 2.0):
        self.half_window = max(1, round(width_deg / 4))
        self.max_delay_ns = int(max_delay_ms * 1e6)
        self.min_frames, self.min_share, self.min_lead = min_frames, min_share, min_lead
        self.wait_ns = int(wait_s * NS)
        self.playing = np.zeros(360)
        self._raw_playing = np.zeros(360)  # the same directions, each in its own bin
        self.quiet = np.zeros(360)
        self.playing_frames = 0
        self.quiet_frames = 0
        self.azimuth_deg: float | None = None
        self._spans: deque[tuple[int, int, bool]] = deque()  # reference chunks: start, end, loud
        self._covered_ns = 0  # the reference is known up to here
        self._pending: deque[_Pending] = deque()

    def reference(self, start_ns: int, end_ns: int, samples: np.ndarray) -> None:
        """A chunk of what the loudspeaker played (float, full scale 1)."""
        if end_ns <= start_ns:
            return
        level = 10 * math.log10(float(np.mean(samples ** 2)) + 1e-20) if len(samples) else -200.0
        self._spans.append((start_ns, end_ns, level >= LOUD_DBFS))
        self._covered_ns = max(self._covered_ns, end_ns)
        self._settle(self._pending[-1].end_ns if self._pending else 0)

    def frame(self, start_ns: int, end_ns: int, azimuths: list[float]) -> None:
        """A localised frame and its directions (an empty list: nothing was found)."""
        self._pending.append(_Pending(start_ns, end_ns, list(azimuths)))
        self._settle(end_ns)

    def _settle(self, newest_ns: int) -> None:
        while self._pending:
            first = self._pending[0]
            if first.end_ns > self._covered_ns and newest_ns - first.end_ns < self.wait_ns:
                return
            self._pending.popleft()
            self._count(first)
        oldest = newest_ns - self.wait_ns - self.max_delay_ns
        while self._spans and self._spans[0][1] < oldest:
            self._spans.popleft()

    def _count(self, frame: _Pending) -> None:
        lo, hi = frame.start_ns - self.max_delay_ns, frame.end_ns
        touching = [(s, e, loud) for s, e, loud in self._spans if e > lo and s < hi]
        loud_ns = sum(min(e, hi) - max(s, lo) for s, e, loud in touching if loud)
        if loud_ns >= PLAYING_SHARE * (hi - lo):
            kind = "playing"
        elif not any(loud for _, _, loud in touching):
            kind = "quiet"
        else:
            return  # the robot started or stopped within reach: neither
        if not frame.azimuths:
            return
        bins = np.zeros(360, dtype=bool)
        for azimuth in frame.azimuths:
            centre = round(azimuth) % 360
            bins[np.arange(centre - self.half_window, centre + self.half_window + 1) % 360] = True
        if kind == "playing":
            self.playing += bins
            self.playing_frames += 1
            for azimuth in frame.azimuths:
                self._raw_playing[round(azimuth) % 360] += 1
            self._estimate()
        else:
            self.quiet += bins
            self.quiet_frames += 1

    def _estimate(self) -> None:
        if self.playing_frames < self.min_frames:
            return
        share = self.playing / self.playing_frames
        score = share - (self.quiet / self.quiet_frames if self.quiet_frames else 0.0)
        peak = int(np.argmax(score))
        if share[peak] < self.min_share or score[peak] < self.min_lead:
            return
        # refine: the circular mean of the playing frames' directions around the peak
        around = np.arange(peak - self.half_window, peak + self.half_window + 1)
        weights = self._raw_playing[around % 360]
        angle = math.atan2(float(np.sum(weights * np.sin(np.radians(around)))),
                           float(np.sum(weights * np.cos(np.radians(around)))))
        self.azimuth_deg = math.degrees(angle) % 360.0

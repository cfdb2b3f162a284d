"""Tracking: directions of successive frames associated into sources with stable ids.

Each frame's directions (best first) are matched greedily to the nearest live track within
``gate_deg`` (circular azimuth distance); a direction no track takes starts a new one. A track
not seen for ``hold_ms`` of capture time ends; its id is never reused within the tracker. A track's
azimuth follows its directions by a circular exponential mean (``smoothing``: weight of the old
value), so one wild frame moves it little.

A track that has lived ``background_s`` (far longer than anyone speaks without a pause: a
loudspeaker, a TV, a dishwasher) is marked background; it takes only directions within half the
gate, so a talker near it starts a track of their own. Its place is remembered for
``background_memory_s`` after it ends, and a new track within half the gate of it is background
from its first frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


def angle_difference_deg(a: float, b: float) -> float:
    """Smallest absolute difference of two azimuths, in [0, 180]."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


@dataclass
class Track:
    source_id: str
    azimuth_deg: float
    first_ns: int
    last_ns: int
    hits: int = 1
    background: bool = False


class Tracker:
    def __init__(self, gate_deg: float = 20.0, hold_ms: float = 1000.0, smoothing: float = 0.6,
                 prefix: str = "s", background_s: float = 0.0, background_memory_s: float = 60.0):
        if not 0 < gate_deg <= 180:
            raise ValueError(f"gate_deg must be in (0, 180], not {gate_deg}")
        if hold_ms < 0:
            raise ValueError(f"hold_ms must not be negative, not {hold_ms}")
        if not 0 <= smoothing < 1:
            raise ValueError(f"smoothing must be in [0, 1), not {smoothing}")
        if background_s < 0 or background_memory_s < 0:
            raise ValueError("background_s and background_memory_s must not be negative")
        self.gate_deg, self.hold_ns, self.smoothing, self.prefix = gate_deg, int(hold_ms * 1e6), smoothing, prefix
        self.background_ns, self.memory_ns = int(background_s * 1e9), int(background_memory_s * 1e9)  # 0: never
        self.places: list[tuple[float, int]] = []  # (azimuth, last seen) of ended background tracks
        self.tracks: list[Track] = []
        self._next_id = 1

    def update(self, time_ns: int, azimuths_deg: list[float]) -> list[Track]:
        """The track each azimuth (best first) belongs to, at capture time ``time_ns``."""
        self.expire(time_ns)
        taken: list[Track] = []
        for azimuth in azimuths_deg:
            free = [t for t in self.tracks if t not in taken
                    and angle_difference_deg(t.azimuth_deg, azimuth) <= self._gate(t)]
            nearest = min(free, key=lambda t: angle_difference_deg(t.azimuth_deg, azimuth), default=None)
            if nearest is None:
                nearest = Track(f"{self.prefix}{self._next_id}", azimuth % 360.0, time_ns, time_ns, 0,
                                background=any(angle_difference_deg(place, azimuth) <= self.gate_deg / 2
                                               for place, _ in self.places))
                self._next_id += 1
                self.tracks.append(nearest)
            else:
                nearest.azimuth_deg = circular_blend(nearest.azimuth_deg, azimuth, self.smoothing)
            nearest.last_ns = time_ns
            nearest.hits += 1
            if self.background_ns and time_ns - nearest.first_ns >= self.background_ns:
                nearest.background = True
            taken.append(nearest)
        return taken

    def _gate(self, track: Track) -> float:
        """A background source does not move: it takes only directions within half the gate, so a
        talker standing near a loudspeaker starts a track of their own."""
        return self.gate_deg / 2 if track.background else self.gate_deg

    def expire(self, time_ns: int) -> None:
        ended = [t for t in self.tracks if time_ns - t.last_ns > self.hold_ns]
        self.tracks = [t for t in self.tracks if time_ns - t.last_ns <= self.hold_ns]
        self.places += [(t.azimuth_deg, t.last_ns) for t in ended if t.background]
        self.places = [(a, seen) for a, seen in self.places if time_ns - seen <= self.memory_ns]


def circular_blend(old_deg: float, new_deg: float, weight_old: float) -> float:
    """Weighted circular mean of two azimuths."""
    x = weight_old * math.cos(math.radians(old_deg)) + (1 - weight_old) * math.cos(math.radians(new_deg))
    y = weight_old * math.sin(math.radians(old_deg)) + (1 - weight_old) * math.sin(math.radians(new_deg))
    return math.degrees(math.atan2(y, x)) % 360.0

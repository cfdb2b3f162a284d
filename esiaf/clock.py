"""How far the orchestrator's clock is from this host's: NTP's on-wire estimate on the heartbeats.

Each heartbeat carries the component's send time ``t1``; the orchestrator's answer echoes it with
its own time ``t2`` (it answers at once, so its send time is ``t2`` too); the component receives
the answer at ``t4``. Then the round trip is ``t4 - t1`` and the offset (orchestrator minus
component) ``t2 - (t1 + t4) / 2``, wrong by at most half the round trip. Of the last
``WINDOW`` samples the one with the shortest round trip is kept (NTP's clock filter: queueing
only ever adds delay), and its half round trip is the uncertainty.

Capture times are stamped with the capturing host's clock; the orchestrator computes latencies
and deadlines on its own, corrected by the capturing component's offset (docs/protocol.md).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

WINDOW = 8  # samples the filter chooses from: 16 s of heartbeats at the default 2 s
MAX_ROUND_TRIP_NS = 10 * 10**9  # an answer slower than this says nothing useful about the clocks


@dataclass(frozen=True)
class Sample:
    offset_ns: int  # orchestrator clock minus this host's
    round_trip_ns: int


class ClockEstimate:
    def __init__(self, window: int = WINDOW) -> None:
        self._samples: deque[Sample] = deque(maxlen=window)

    def add(self, sent_ns: int, orchestrator_ns: int, received_ns: int) -> None:
        """One heartbeat's round trip: sent and received on this host's clock, answered at
        ``orchestrator_ns`` on the orchestrator's. Ignored if the times cannot be right."""
        round_trip = received_ns - sent_ns
        if 0 <= round_trip <= MAX_ROUND_TRIP_NS:
            self._samples.append(Sample(orchestrator_ns - (sent_ns + received_ns) // 2, round_trip))

    @property
    def best(self) -> Sample | None:
        return min(self._samples, key=lambda s: s.round_trip_ns, default=None)

    def report(self) -> dict[str, int] | None:
        """What the next heartbeat tells the orchestrator: the offset and its uncertainty."""
        best = self.best
        return None if best is None else {"offset_ns": best.offset_ns, "uncertainty_ns": best.round_trip_ns // 2}

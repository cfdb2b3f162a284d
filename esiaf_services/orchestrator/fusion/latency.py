"""Per-component latency (time received − end of the audio a result covers) and the timeout
a fusion grants each component: the larger of factor × its running mean latency and the mean plus
``deviations`` × its running mean deviation (as TCP's retransmission timeout, RFC 6298: a component
whose latency varies, e.g. on a loaded machine, is granted the spread it has shown), clamped; an
initial timeout before any latency is known."""
from __future__ import annotations

from dataclasses import dataclass

from ..settings import TimeoutSettings

MEAN_WINDOW = 100  # the running mean is exact over the first 100 results, then exponential
DEVIATION_WINDOW = 4  # the deviation follows faster (RFC 6298's beta = 1/4): load comes and goes


@dataclass
class Latency:
    count: int = 0
    mean_ns: float = 0.0
    deviation_ns: float = 0.0  # running mean absolute deviation from the mean (not persisted: relearnt)
    deviations: int = 0  # samples of it

    def add(self, latency_ns: int) -> None:
        if self.count:
            self.deviations += 1
            self.deviation_ns += (abs(latency_ns - self.mean_ns) - self.deviation_ns) / min(self.deviations,
                                                                                           DEVIATION_WINDOW)
        self.count += 1
        self.mean_ns += (latency_ns - self.mean_ns) / min(self.count, MEAN_WINDOW)


class Latencies:
    """Running mean latency of every component that has sent results, and its timeout."""

    def __init__(self, settings: TimeoutSettings) -> None:
        self.settings = settings
        self.by_component: dict[str, Latency] = {}
        self.changed: set[str] = set()  # to persist at the next commit

    def add(self, component: str, latency_ns: int) -> None:
        latency = self.by_component.get(component)
        if latency is None:
            latency = self.by_component[component] = Latency()
        latency.add(latency_ns)
        self.changed.add(component)

    def restore(self, component: str, count: int, mean_ns: float) -> None:
        self.by_component[component] = Latency(count, mean_ns)

    def timeout_ns(self, component: str) -> int:
        settings = self.settings
        latency = self.by_component.get(component)
        if latency is None or latency.count == 0:
            return int(settings.initial_s * 1e9)
        factor = settings.factors.get(component, settings.factor)
        wanted_ns = max(factor * latency.mean_ns, latency.mean_ns + settings.deviations * latency.deviation_ns)
        seconds = min(max(wanted_ns / 1e9, settings.min_s), settings.max_s)
        return int(seconds * 1e9)

    def take_changed(self) -> list[tuple[str, Latency]]:
        changed = [(name, self.by_component[name]) for name in sorted(self.changed)]
        self.changed.clear()
        return changed


def percentile(values: list[float], q: float) -> float | None:
    """The q-quantile (0..1) by linear interpolation; None for no values."""
    ordered = sorted(values)
    if not ordered:
        return None
    k = (len(ordered) - 1) * q
    lo = int(k)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)

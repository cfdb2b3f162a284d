"""Per-component latency (time received − end of the audio a result covers) and the timeout
a fusion grants each component: factor × its running mean latency, clamped, or an initial
timeout before any latency is known."""
from __future__ import annotations

from dataclasses import dataclass

from .settings import TimeoutSettings

MEAN_WINDOW = 100  # the running mean is exact over the first 100 results, then exponential


@dataclass
class Latency:
    count: int = 0
    mean_ns: float = 0.0

    def add(self, latency_ns: int) -> None:
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
        seconds = min(max(factor * latency.mean_ns / 1e9, settings.min_s), settings.max_s)
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

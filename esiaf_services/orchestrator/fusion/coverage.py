"""What fusion remembers of each stream: the audio each component has covered (with results or
``nothing``), and the results of fused types by span, both kept for a horizon of capture time."""
from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol

from .aggregate import overlaps

GAP_TOLERANCE_NS = 1_000_000  # spans closer than 1 ms count as contiguous (rounding of stamps)


@dataclass(frozen=True)
class StoredResult:
    """A result as stored: its id, what fusion selects on, and its JSON."""

    id: int
    component: str
    type: str
    stream_id: str
    start_ns: int
    end_ns: int
    json: dict[str, Any]

    @classmethod
    def from_json(cls, value: dict[str, Any]) -> StoredResult:
        return cls(id=value["id"], component=value["component"], type=value["type"],
                   stream_id=value["stream_id"], start_ns=value["span"]["start_ns"],
                   end_ns=value["span"]["end_ns"], json=value)

    @property
    def is_nothing(self) -> bool:
        return "nothing" in self.json


class Coverage:
    """The audio one component has reported on, as disjoint sorted intervals."""

    def __init__(self) -> None:
        self.starts: list[int] = []
        self.ends: list[int] = []

    def add(self, start_ns: int, end_ns: int) -> None:
        starts, ends = self.starts, self.ends
        # intervals touching [start - tol, end + tol] merge with it
        lo = bisect.bisect_left(ends, start_ns - GAP_TOLERANCE_NS)
        hi = bisect.bisect_right(starts, end_ns + GAP_TOLERANCE_NS)
        if lo < hi:
            start_ns = min(start_ns, starts[lo])
            end_ns = max(end_ns, ends[hi - 1])
        starts[lo:hi] = [start_ns]
        ends[lo:hi] = [end_ns]

    def covers(self, start_ns: int, end_ns: int) -> bool:
        """Reported on contiguously (gaps under GAP_TOLERANCE_NS) from ``start_ns`` to ``end_ns``."""
        i = bisect.bisect_right(self.starts, start_ns + GAP_TOLERANCE_NS) - 1
        return i >= 0 and self.ends[i] + GAP_TOLERANCE_NS >= end_ns and self.ends[i] >= start_ns

    def forget_before(self, horizon_ns: int) -> None:
        """Drops intervals that end before ``horizon_ns``."""
        cut = bisect.bisect_left(self.ends, horizon_ns)
        if cut:
            del self.starts[:cut], self.ends[:cut]


class Spanned(Protocol):
    @property
    def id(self) -> int: ...
    @property
    def start_ns(self) -> int: ...
    @property
    def end_ns(self) -> int: ...


class SpanIndex:
    """Things with a span in one stream (results of one type, published fusions), sorted by
    start, for overlap lookups."""

    def __init__(self) -> None:
        self._keys: list[tuple[int, int]] = []  # (start_ns, id)
        self._results: list[Any] = []
        self._longest_ns = 0

    def add(self, result: Spanned) -> None:
        key = (result.start_ns, result.id)
        i = bisect.bisect_right(self._keys, key)
        self._keys.insert(i, key)
        self._results.insert(i, result)
        self._longest_ns = max(self._longest_ns, result.end_ns - result.start_ns)

    def overlapping(self, start_ns: int, end_ns: int) -> Iterator[Any]:
        lo = bisect.bisect_left(self._keys, (start_ns - self._longest_ns, -1))
        hi = bisect.bisect_right(self._keys, (end_ns, float("inf")))
        for result in self._results[lo:hi]:
            if overlaps(result.start_ns, result.end_ns, start_ns, end_ns):
                yield result

    def remove(self, result: Spanned) -> None:
        """Takes ``result`` out (before its span changes), if it is there."""
        i = bisect.bisect_left(self._keys, (result.start_ns, result.id))
        if i < len(self._keys) and self._keys[i] == (result.start_ns, result.id):
            del self._keys[i], self._results[i]

    def forget_before(self, horizon_ns: int) -> None:
        """Drops what starts before ``horizon_ns - longest`` (it ends before the horizon)."""
        cut = bisect.bisect_left(self._keys, (horizon_ns - self._longest_ns, -1))
        if cut:
            del self._keys[:cut], self._results[:cut]

    def __len__(self) -> int:
        return len(self._results)

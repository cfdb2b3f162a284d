"""Fusion: turns stored results into fused results.

This first engine publishes every anchor result at once, alone (``fuse: []``).
Gathering results of other types around an anchor, waiting for them and timing
out is the fusion-engine work; a configured fusion that asks for it is refused
at start-up rather than faked. A fuller engine replaces :class:`FusionEngine`
with the same three methods.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable

from .settings import FusionSettings


class FusionConfigError(Exception):
    """A configured fusion this engine cannot run: the message says which and why."""


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


@dataclass(frozen=True)
class FusedResult:
    id: int
    revision: int
    fusion: str
    stream_id: str
    start_ns: int  # the anchor's span
    end_ns: int
    published_ns: int
    json: dict[str, Any]


class FusionEngine:
    def __init__(self, fusions: Iterable[FusionSettings], allocate_id: Callable[[], int],
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.fusions = list(fusions)
        for fusion in self.fusions:
            if fusion.fuse:
                raise FusionConfigError(
                    f"fusion {fusion.name!r}: fusing other result types with the {fusion.anchor} "
                    f"anchor (fuse: {', '.join(fusion.fuse)}) is not implemented yet; it comes "
                    "with the fusion-engine work. Configure fuse: [] for now.")
        self._allocate_id = allocate_id
        self._clock_ns = clock_ns

    def on_result(self, result: StoredResult) -> list[FusedResult]:
        """Fused results that ``result`` completes, to store and publish in this order."""
        fused = []
        if "nothing" in result.json:  # "covered, no result" (nothing recognised): coverage, not an answer
            return fused
        for fusion in self.fusions:
            if fusion.anchor != result.type:
                continue
            if fusion.stream is not None and fusion.stream != result.stream_id:
                continue
            fused.append(self._publish_alone(fusion, result))
        return fused

    def on_component_gone(self, component: str) -> list[FusedResult]:
        """A component died or left: fusions stop waiting for it. Nothing waits here yet."""
        return []

    def _publish_alone(self, fusion: FusionSettings, anchor: StoredResult) -> FusedResult:
        fused_id = self._allocate_id()
        published_ns = self._clock_ns()
        return FusedResult(
            id=fused_id, revision=1, fusion=fusion.name, stream_id=anchor.stream_id,
            start_ns=anchor.start_ns, end_ns=anchor.end_ns, published_ns=published_ns,
            json={"type": "fused_result", "id": fused_id, "revision": 1, "fusion": fusion.name,
                  "stream_id": anchor.stream_id, "anchor": anchor.json, "results": {},
                  "completion": "complete", "missing_components": [],
                  "published_ns": published_ns})

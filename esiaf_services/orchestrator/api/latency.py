"""Per-component latency statistics (time received − end of the audio a result covers)."""
from __future__ import annotations

from typing import overload

from fastapi import APIRouter, Depends, Query

from ..core import Orchestrator
from ..fusion.latency import percentile
from .deps import get_core
from .models import LatencyInfo, LatencyList

router = APIRouter(tags=["results"])

PERCENTILE_RESULTS = 1000  # p50 and p95 are over each component's last 1000 results


@overload
def _ms(value_ns: float) -> float: ...
@overload
def _ms(value_ns: None) -> None: ...
def _ms(value_ns: float | None) -> float | None:
    return None if value_ns is None else round(value_ns / 1e6, 3)


@router.get("/latency", response_model=LatencyList,
            summary="each component's latency: running mean (as timeouts use it), p50, p95",
            description=f"p50 and p95 are over the last {PERCENTILE_RESULTS} results; timeout_ms "
                        "is how long a fusion now waits for the component after the window ends.")
async def list_latency(component: str | None = Query(None, description="component name"),
                       core: Orchestrator = Depends(get_core)) -> LatencyList:
    latencies = core.ingest.engine.latencies
    items = []
    for name, latency in sorted(latencies.by_component.items()):
        if component is not None and name != component:
            continue
        recent = [float(v) for v in core.store.recent_latencies_ns(name, PERCENTILE_RESULTS)]
        items.append(LatencyInfo(
            component=name, count=latency.count, mean_ms=_ms(latency.mean_ns),
            p50_ms=_ms(percentile(recent, 0.5)), p95_ms=_ms(percentile(recent, 0.95)),
            timeout_ms=_ms(latencies.timeout_ns(name))))
    return LatencyList(items=items)

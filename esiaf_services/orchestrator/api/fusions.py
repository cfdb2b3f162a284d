"""The configured fusions (readable and replaceable), their counters and fusion overhead."""
from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException

from ..core import Orchestrator
from ..fusion.latency import percentile
from .deps import get_core
from .models import FusionList, FusionStats

router = APIRouter(tags=["fusions"])


@router.get("/fusions", response_model=FusionList, summary="the configured fusions")
async def list_fusions(core: Orchestrator = Depends(get_core)) -> FusionList:
    return FusionList(items=core.ingest.engine.fusions)


@router.put("/fusions", response_model=FusionList,
            summary="replace the configured fusions (until restart; the config file is not changed)",
            description="Anchors that arrive from now on open fusions of the new list; fusions "
                        "already open finish under the configuration they were opened with.")
async def replace_fusions(body: FusionList, core: Orchestrator = Depends(get_core)) -> FusionList:
    names = [f.name for f in body.items]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise HTTPException(422, f"fusion names must be unique; repeated: {', '.join(repeated)}")
    core.ingest.engine.replace_fusions(body.items)
    return FusionList(items=core.ingest.engine.fusions)


@router.get("/fusions/stats", response_model=FusionStats,
            summary="results ingested, fused results by completion, fusion overhead")
async def fusion_stats(core: Orchestrator = Depends(get_core)) -> FusionStats:
    ingest = core.ingest
    overhead_ms = [value / 1e6 for value in ingest.overhead_ns]
    lateness_ms = [value / 1e6 for value in ingest.timer_lateness_ns]
    return FusionStats(
        counters=dict(ingest.counters), open_fusions=len(ingest.engine.open),
        overhead_samples=len(overhead_ms), overhead_p50_ms=percentile(overhead_ms, 0.5),
        overhead_p99_ms=percentile(overhead_ms, 0.99), timed_out_samples=len(lateness_ms),
        timer_lateness_p50_ms=percentile(lateness_ms, 0.5),
        timer_lateness_p99_ms=percentile(lateness_ms, 0.99))

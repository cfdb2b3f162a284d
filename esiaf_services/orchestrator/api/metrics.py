"""GET /metrics: Prometheus text format (docs/dashboard.md has a scrape config)."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..core import Orchestrator
from .deps import get_core

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response,
            summary="counters, gauges and latency histograms in the Prometheus text format",
            description="Per component (from its heartbeats) and stream: results, fused results by "
                        "completion, lost, bad and refused messages, latency histograms, fusion overhead, "
                        "heartbeat age, queue depths.")
async def metrics(core: Orchestrator = Depends(get_core)) -> Response:
    return Response(generate_latest(core.metrics.registry), media_type=CONTENT_TYPE_LATEST)

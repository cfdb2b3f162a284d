"""What the routers share: the running orchestrator, and query checks."""
from __future__ import annotations

from typing import Annotated

from fastapi import HTTPException, Query, Request

from esiaf.result_checks import MAX_TIME_NS

from ..core import Orchestrator

# Bounds of numbers that reach SQLite, whose integers end at 2**63 - 1 (past it a query failed: a
# 500): capture times as results have them (1970..2116), ids and sequence numbers below 2**53 (a
# JSON number any client reads exactly).
TimeNs = Annotated[int | None, Query(ge=0, le=MAX_TIME_NS, description="ns since the epoch (1970..2116)")]
MAX_ID = 2**53


def get_core(request: Request) -> Orchestrator:
    return request.app.state.core


def check_range(start_ns: int | None, end_ns: int | None) -> None:
    if start_ns is not None and end_ns is not None and start_ns > end_ns:
        raise HTTPException(422, f"start_ns ({start_ns}) is after end_ns ({end_ns})")

"""What the routers share: the running orchestrator, and query checks."""
from __future__ import annotations

from fastapi import HTTPException, Request

from ..core import Orchestrator


def get_core(request: Request) -> Orchestrator:
    return request.app.state.core


def check_range(start_ns: int | None, end_ns: int | None) -> None:
    if start_ns is not None and end_ns is not None and start_ns > end_ns:
        raise HTTPException(422, f"start_ns ({start_ns}) is after end_ns ({end_ns})")

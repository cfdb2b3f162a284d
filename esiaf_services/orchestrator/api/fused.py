"""GET /fused: the stored fused results, the latest revision of each (the robot's own voice left out unless
asked for)."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Response

from ..core import Orchestrator
from .deps import MAX_ID, TimeNs, check_range, get_core
from .models import FusedPage

router = APIRouter(tags=["fused"])


@router.get("/fused", response_model=FusedPage,
            summary="fused results, oldest first, whose anchor span overlaps [start_ns, end_ns]",
            description="The latest revision of each. Live: websocket /ws/fused?stream=&fusion="
                        "&after_id=&include_robot= sends the stored fused results after after_id, then each "
                        'one as it is published, {"type": "stream_end", "stream_id": ...} events and '
                        '{"type": "barge_in", ...} events (docs/protocol.md). Without include_robot=true, '
                        "fused results of the robot's own voice are left out.")
async def list_fused(
        stream: str | None = Query(None, description="stream_id"),
        fusion: str | None = Query(None, description="fusion name"),
        start_ns: TimeNs = None,
        end_ns: TimeNs = None,
        after_id: int | None = Query(None, ge=0, le=MAX_ID, description="only fused results with a larger id"),
        limit: int = Query(100, ge=1, le=1000),
        include_robot: bool = Query(False, description='also the robot\'s own voice heard back ("source": '
                                    '"robot")'),
        core: Orchestrator = Depends(get_core)) -> Response:
    check_range(start_ns, end_ns)
    page = core.store.query_fused(fusion=fusion, stream=stream, start_ns=start_ns,
                                  end_ns=end_ns, after_id=after_id, limit=limit, include_robot=include_robot)
    if page.next_after_id is None:
        page = type(page)(items=[], next_after_id=after_id)
    return Response(page.to_json(), media_type="application/json")

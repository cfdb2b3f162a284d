from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Response

from ..core import Orchestrator
from ..settings import ResultTypeName
from .deps import MAX_ID, TimeNs, check_range, get_core
from .models import ResultPage

router = APIRouter(tags=["results"])


@router.get("/results", response_model=ResultPage,
            summary="raw results, oldest first, whose span overlaps [start_ns, end_ns]")
async def list_results(
        type_name: ResultTypeName | None = Query(None, alias="type"),
        component: str | None = Query(None, description="component name"),
        stream: str | None = Query(None, description="stream_id"),
        start_ns: TimeNs = None,
        end_ns: TimeNs = None,
        after_id: int | None = Query(None, ge=0, le=MAX_ID, description="only results with a larger id"),
        limit: int = Query(100, ge=1, le=1000),
        core: Orchestrator = Depends(get_core)) -> Response:
    check_range(start_ns, end_ns)
    page = core.store.query_results(type_name=type_name, component=component, stream=stream,
                                    start_ns=start_ns, end_ns=end_ns, after_id=after_id,
                                    limit=limit)
    if page.next_after_id is None:
        page = type(page)(items=[], next_after_id=after_id)
    # Stored JSON is sent as it is: no decoding and re-encoding in the event loop.
    return Response(page.to_json(), media_type="application/json")

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from .models import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, response_model_exclude_none=True,
            summary="ok while results can be stored",
            responses={503: {"description": "the database cannot be written: results are queued "
                                            "(bounded) until it can; the detail says why"}})
async def health(request: Request):
    # The app only serves once its lifespan has started the orchestrator.
    store = request.app.state.core.store
    if store.error is not None:
        return JSONResponse(status_code=503, content={"status": "unhealthy", "detail": store.error})
    return Health(status="ok", recovered=request.app.state.core.recovered or None)

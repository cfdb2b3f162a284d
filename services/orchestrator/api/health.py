from __future__ import annotations

from fastapi import APIRouter

from ..models import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, summary="ok once registrations are accepted")
async def health() -> Health:
    # The app only serves once its lifespan has started the orchestrator.
    return Health(status="ok")

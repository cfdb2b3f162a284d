from __future__ import annotations

from fastapi import APIRouter, Depends

from ..core import Orchestrator
from ..models import FusionList
from .deps import get_core

router = APIRouter(tags=["fusions"])


@router.get("/fusions", response_model=FusionList, summary="the configured fusions")
async def list_fusions(core: Orchestrator = Depends(get_core)) -> FusionList:
    return FusionList(items=core.settings.fusions)

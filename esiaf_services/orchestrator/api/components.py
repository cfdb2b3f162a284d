from __future__ import annotations

import math

from fastapi import APIRouter, Depends, HTTPException, Query, Response, status

from ..core import Orchestrator
from ..registry.components import Component, InstanceConflict, TopicConflict
from .deps import get_core
from .models import (
    ComponentInfo,
    ComponentList,
    Problem,
    RegisterRequest,
    RegisterResponse,
    ServiceInfo,
    TopicDeclaration,
)

router = APIRouter(tags=["components"])


def _declarations(topics: dict) -> list[TopicDeclaration]:
    return [TopicDeclaration(topic=topic, format=fmt) for topic, fmt in topics.items()]


def component_info(component: Component) -> ComponentInfo:
    return ComponentInfo(
        component_id=component.component_id, name=component.name,
        kind=component.kind, designation=component.kind, stream_id=component.stream_id,
        status=component.status, inputs=_declarations(component.inputs),
        outputs=_declarations(component.outputs), audio_endpoint=component.audio_endpoint,
        audio_public_key=component.audio_public_key, host=component.host, pid=component.pid, info=component.info,
        registered_ns=component.registered_ns, last_seen_ns=component.last_seen_ns,
        departed_ns=component.departed_ns, heartbeats=component.heartbeats,
        results_received=component.results_received, stats=component.stats,
        heartbeat_interval_s=component.beat_interval_s,
        clock_offset_ms=None if component.clock_offset_ns is None else component.clock_offset_ns / 1e6,
        clock_uncertainty_ms=None if component.clock_uncertainty_ns is None else component.clock_uncertainty_ns / 1e6)


@router.post("/components", status_code=status.HTTP_201_CREATED, response_model=RegisterResponse,
             responses={409: {"model": Problem, "description": "a topic's channel count differs, or the "
                              "instance id is held by a live instance (then with Retry-After: it may be "
                              "declared dead by then)"}},
             summary="register an instance of a component")
async def register(request: RegisterRequest,
                   core: Orchestrator = Depends(get_core)) -> RegisterResponse:
    try:
        component = await core.register(
            name=request.name, kind=request.kind, stream_id=request.stream_id,
            inputs={d.topic: d.format.model_dump() for d in request.inputs},
            outputs={d.topic: d.format.model_dump() for d in request.outputs},
            audio_endpoint=request.audio_endpoint, host=request.host, pid=request.pid,
            info=request.info, audio_public_key=request.audio_public_key, instance=request.instance,
            incarnation=request.incarnation)
    except TopicConflict as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except InstanceConflict as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc),
                            headers={"Retry-After": str(math.ceil(core.settings.dead_after_s))}) from None
    state = component.pushed_state
    assert state is not None  # register() gives a new component its state
    return RegisterResponse(
        component_id=component.component_id, control_endpoint=core.control_endpoint,
        control_key=component.control_key, key_id=component.key_id,
        results_endpoint=core.results_endpoint,
        heartbeat_interval_s=core.settings.heartbeat_interval_s,
        dead_after_s=core.settings.dead_after_s, idle_heartbeat_interval_s=core.settings.idle_heartbeat_interval_s,
        peers=state.peers, formats=state.formats,
        peer_keys=state.peer_keys or {}, streams=state.streams, consumers=state.consumers)


@router.get("/components", response_model=ComponentList,
            summary="live components with their last heartbeat statistics")
async def list_components(
        include_dead: bool = Query(False, description="also the dead and replaced ones"),
        core: Orchestrator = Depends(get_core)) -> ComponentList:
    registry = core.registry
    services = {name: ServiceInfo(instances=[c.component_id for c in registry.instances(name)],
                                  serving=registry.assignments.serving(name))
                for name in dict.fromkeys(c.name for c in registry.all())}
    return ComponentList(items=[component_info(c) for c in registry.all(include_dead)], services=services)


@router.delete("/components/{component_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses={404: {"model": Problem, "description": "no such live component"}},
               summary="remove a component (its clean shutdown)")
async def remove(component_id: str, core: Orchestrator = Depends(get_core)) -> Response:
    if await core.remove(component_id) is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no live component {component_id!r}")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/components/{component_id}/dead", status_code=status.HTTP_204_NO_CONTENT,
             responses={404: {"model": Problem, "description": "no such live component"}},
             summary="report a component dead (its process died: its launcher saw it exit)")
async def report_dead(component_id: str, core: Orchestrator = Depends(get_core)) -> Response:
    """What a silent component's `dead_after_s` would do, at once: fusions stop waiting for it, its
    streams move to another instance, the utterances it had not answered are fused without it."""
    if await core.declare_dead(component_id) is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no live component {component_id!r}")
    return Response(status_code=status.HTTP_204_NO_CONTENT)

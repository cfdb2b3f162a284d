"""Streams: capture sessions, announced by their sources when capture starts.

A stream's ``start_ns`` is the capture time of its first sample, so a client can
turn any span into a position in the recording (``(start_ns - stream.start_ns) / 1e9``).
"""
from __future__ import annotations

import json
import sqlite3
import time
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Path
from pydantic import BaseModel, ConfigDict, Field

from esiaf.result_checks import MAX_TIME_NS

from ..core import Orchestrator
from .deps import get_core
from .models import Problem

router = APIRouter(tags=["streams"])


class StreamAnnouncement(BaseModel):
    model_config = ConfigDict(extra="forbid")
    start_ns: int = Field(gt=0, le=MAX_TIME_NS,
                          description="capture time of the stream's first sample (ns since the epoch)")
    source: str = Field(default="", description="the component instance that captures it (its component_id)")
    info: dict[str, Any] = Field(default_factory=dict, examples=[{"input": "speech.wav"}])


class Stream(StreamAnnouncement):
    stream_id: str
    announced_ns: int


class StreamList(BaseModel):
    items: list[Stream]


def _stream(row: tuple) -> Stream:
    stream_id, start_ns, source, announced_ns, info = row
    return Stream(stream_id=stream_id, start_ns=start_ns, source=source, announced_ns=announced_ns,
                  info=json.loads(info))


@router.put("/streams/{stream_id}", response_model=Stream, summary="announce a stream (sources do this)",
            responses={503: {"model": Problem, "description": "the database cannot be written"}})
async def announce(body: StreamAnnouncement, stream_id: str = Path(min_length=1),
                   core: Orchestrator = Depends(get_core)) -> Stream:
    try:
        core.store.put_stream(stream_id=stream_id, start_ns=body.start_ns, source=body.source,
                              announced_ns=time.time_ns(), info_json=json.dumps(body.info))
    except sqlite3.Error as exc:
        raise HTTPException(503, f"the stream cannot be recorded: database {core.store.path} cannot be "
                                 f"written ({exc})") from None
    core.ingest.on_stream_announced(stream_id, body.source, body.info)
    await core.stream_announced(stream_id)
    return _stream(core.store.streams(stream_id)[0])


@router.get("/streams", response_model=StreamList, summary="every announced stream")
async def list_streams(core: Orchestrator = Depends(get_core)) -> StreamList:
    return StreamList(items=[_stream(row) for row in core.store.streams()])


@router.get("/streams/{stream_id}", response_model=Stream, summary="one stream",
            responses={404: {"model": Problem, "description": "no such stream has been announced"}})
async def get_stream(stream_id: str, core: Orchestrator = Depends(get_core)) -> Stream:
    rows = core.store.streams(stream_id)
    if not rows:
        raise HTTPException(404, f"no stream {stream_id!r} has been announced")
    return _stream(rows[0])

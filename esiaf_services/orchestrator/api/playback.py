"""The robot's voice, per stream: say or play through the stream's player, stop it, what it plays, and the
barge-in policy (planes/players.py sends the orders over the control plane, docs/protocol.md "Commands").

Every order is queued at the player after what it already plays; its effect shows in the stream's
``playback`` results and in ``GET /streams/{stream}/playing``. A stream without a player is a 404, one
whose player has not connected its control channel yet a 409, both with the reason.
"""
from __future__ import annotations

import asyncio
import sqlite3
from typing import Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Request
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from esiaf.control_messages import MAX_PCM_BYTES, MAX_TEXT, BargeInPolicy, Play, PlayerOrder, Say, StopPlaying

from ..core import Orchestrator
from ..planes.players import NoPlayer
from .deps import get_core
from .models import Problem
from .wav import read_wav, resample

router = APIRouter(tags=["robot"])
MAX_PLAY_SAMPLES = MAX_PCM_BYTES // 2  # 16-bit at the player's rate: 21.8 s at 16 kHz
NO_PLAYER: dict[int | str, dict[str, Any]] = {
    404: {"model": Problem, "description": "no player is registered for the stream"},
    409: {"model": Problem, "description": "its player has not connected its control channel yet"}}


class SayRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    text: str = Field(min_length=1, max_length=MAX_TEXT, description="what the robot says")
    voice: str = Field(default="slt", max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$",
                       description="the TTS voice (flite: kal, slt, rms, awb, ...)")


class Ordered(BaseModel):
    stream_id: str
    player: str = Field(description="the player's component_id")
    order: str = Field(description="say, play or stop")
    seconds: float | None = Field(default=None, description="play: the sound's length at the player's rate")


class PlayingItem(BaseModel):
    name: str = Field(description='what plays: a file name, "say: <text>", or the name given to POST .../play')
    item: int = Field(default=0, description="its number at the player (its playback results carry it)")
    start_ns: int = Field(description="capture time it started playing")
    end_ns: int = Field(description="capture time it is to end")


class Playing(BaseModel):
    stream_id: str
    player: str
    playing: PlayingItem | None = Field(description="what plays now (the player's last heartbeat); null: nothing")
    barge_in: BargeInPolicy = Field(description="the stream's barge-in policy")


class BargeInSetting(BaseModel):
    model_config = ConfigDict(extra="forbid")
    policy: BargeInPolicy = Field(description="stop: the player stops; duck: it plays the rest lower; ignore")


def _order(core: Orchestrator, stream: str, order: PlayerOrder, seconds: float | None = None) -> Ordered:
    try:
        player = core.players.order(stream, order)
    except NoPlayer as exc:
        raise HTTPException(exc.status, str(exc)) from None
    return Ordered(stream_id=stream, player=player.component_id, order=order.action, seconds=seconds)


@router.post("/streams/{stream}/say", response_model=Ordered, status_code=202, responses=NO_PLAYER,
             summary="the stream's robot says a sentence (queued after what it plays)")
async def say(stream: str, body: SayRequest, core: Orchestrator = Depends(get_core)) -> Ordered:
    return _order(core, stream, Say(text=body.text, voice=body.voice))


@router.post("/streams/{stream}/play", response_model=Ordered, status_code=202,
             responses={**NO_PLAYER, 413: {"model": Problem, "description": "longer than the cap"},
                        422: {"model": Problem, "description": "not a WAV file the robot can play"}},
             openapi_extra={"requestBody": {"required": True, "content": {"audio/wav": {"schema": {
                 "type": "string", "format": "binary"}}}}},
             summary="the stream's robot plays a WAV file (the body; any rate, mono or stereo mixed down; at most "
                     f"{MAX_PLAY_SAMPLES} samples at the player's rate, {MAX_PLAY_SAMPLES / 16000:.1f} s at 16 kHz)")
async def play(stream: str, request: Request, name: str = "", core: Orchestrator = Depends(get_core)) -> Ordered:
    data = await request.body()
    if not data:
        raise HTTPException(422, "no audio: send a WAV file as the request body")
    source_rate, samples = await asyncio.to_thread(read_wav, data, 2)
    if samples.size == 0:
        raise HTTPException(422, "audio has no samples")
    try:
        player = core.players.player_of(stream)
    except NoPlayer as exc:
        raise HTTPException(exc.status, str(exc)) from None
    rate_hz = _player_rate(player.outputs)
    if round(samples.size * rate_hz / source_rate) > MAX_PLAY_SAMPLES:
        raise HTTPException(413, f"audio is {samples.size / source_rate:.1f} s long; at the player's {rate_hz} Hz "
                                 f"at most {MAX_PLAY_SAMPLES / rate_hz:.1f} s ({MAX_PLAY_SAMPLES} samples) are taken "
                                 "at once: send it in parts")
    played = np.clip(await asyncio.to_thread(resample, samples, source_rate, rate_hz), -1.0, 1.0)
    pcm = np.clip(np.rint(played * 32767), -32768, 32767).astype("<i2").tobytes()
    return _order(core, stream, Play(name=name[:256] or "wav", pcm=pcm), round(played.size / rate_hz, 3))


def _player_rate(outputs: dict[str, Any]) -> int:
    """The rate the player plays at: its output's."""
    for fmt in outputs.values():
        return int(fmt.get("sample_rate_hz", 16000))
    return 16000


@router.delete("/streams/{stream}/playing", response_model=Ordered, status_code=202, responses=NO_PLAYER,
               summary="the stream's robot stops what it plays and forgets what is queued")
async def stop(stream: str, core: Orchestrator = Depends(get_core)) -> Ordered:
    return _order(core, stream, StopPlaying())


@router.get("/streams/{stream}/playing", response_model=Playing, responses=NO_PLAYER,
            summary="what the stream's robot plays now, its span in capture time, or null")
async def playing(stream: str, core: Orchestrator = Depends(get_core)) -> Playing:
    try:
        player, item = core.players.playing(stream)
    except NoPlayer as exc:
        raise HTTPException(exc.status, str(exc)) from None
    try:  # a heartbeat's info is the player's word: one that is not an item reads as nothing playing
        now = PlayingItem.model_validate(item) if item else None
    except ValidationError:
        now = None
    return Playing(stream_id=stream, player=player.component_id, playing=now, barge_in=core.players.policy(stream))


@router.get("/streams/{stream}/barge-in", response_model=BargeInSetting,
            summary="the stream's barge-in policy (the orchestrator's barge_in_policy unless set)")
async def get_barge_in(stream: str, core: Orchestrator = Depends(get_core)) -> BargeInSetting:
    return BargeInSetting(policy=core.players.policy(stream))


@router.put("/streams/{stream}/barge-in", response_model=BargeInSetting,
            summary="what the stream's player does when a person starts speaking while it plays (kept across "
                    "restarts)",
            responses={503: {"model": Problem, "description": "the database cannot be written"}})
async def put_barge_in(stream: str, body: BargeInSetting, core: Orchestrator = Depends(get_core)) -> BargeInSetting:
    try:
        core.players.set_policy(stream, body.policy)
    except sqlite3.Error as exc:
        raise HTTPException(503, f"the policy cannot be kept: database {core.store.path} cannot be written "
                                 f"({exc})") from None
    return body

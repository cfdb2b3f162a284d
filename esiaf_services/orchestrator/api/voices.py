"""Enrolled voices: the ``/voices`` routes (the table is store/voices.py).

A voice is a name and one or more speaker embeddings (unit length, each tagged with the encoder
that made it: ``ge2e``, ``dvector`` or ``fused``, ``esiaf/speech/speaker/encoders.py``; a voiceid
asks only for its own encoder's and never compares two encoders' embeddings). They live in the
orchestrator's SQLite file, in a table of their own, and every voiceid instance asks
``GET /voices?embeddings=1&encoder=...&wait_s=30`` with the ETag it last saw: a long poll, answered
at once when the voices differ from that ETag, else when they change (an enrolment, a learnt
embedding or a deletion here), when the server shuts down, or with a 304 after ``wait_s`` — so an
enrolment reaches every voiceid at once, and an idle voiceid and orchestrator do not wake every
second to ask.

``POST /voices/{name}`` adds embeddings from a WAV of any rate (multipart field ``audio``,
embedded here with every encoder, so a voiceid of any model finds it: enrolment then works whether
or not a voiceid runs), from a past utterance (JSON ``{"stream", "start_ns", "end_ns"}``: the
embeddings of the stored ``voice_id`` results overlapping that span), or from an anonymous voice
(JSON ``{"stream", "anonymous": "voice-2"}``: every stored result of that stream with that label);
the JSON forms take ``"encoder"``, the voiceid's model that made those results (default
``DEFAULT_MODEL``; a 512-float embedding is ``fused``'s). A WAV is also enrolled as
``enrolment_room_copies`` (default 0: off) reverberant noisy copies of itself, each in a simulated room
(``esiaf/speech/speaker/augment.py`` room_copies; source ``wav-room``, beside the clean one's
``wav``), so a voice enrolled from a clean recording is known across a room; the voiceid scores
them as it scores every enrolled embedding. Without pyroomacoustics the clean one alone is enrolled
(said once in the log, and ``room_copies`` 0 in the answer).

``POST /voices/{name}/learnt`` is the voiceid's: an embedding of an utterance it identified as that
voice with a margin (``{"encoder", "embedding"}``), kept as ``learnt`` (bounded per voice; never
creates a voice). ``POST /voices/{name}/forget-learnt`` deletes a voice's learnt embeddings.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field, StrictInt, TypeAdapter, ValidationError

from esiaf.api_client import VOICES_MAX_WAIT_S
from esiaf.printable import name_problem, printable
from esiaf.result_checks import MAX_TIME_NS
from esiaf.speech.speaker.encoders import DEFAULT_MODEL, MODELS, SIZES, Model

from ..core import Orchestrator
from ..store.voices import LEARNT, VoiceLimit, VoiceTable
from .deps import get_core
from .models import Problem
from .wav import read_wav, resample

router = APIRouter(tags=["voices"])
ENCODER_RATE_HZ = 16000
MIN_ENROL_SPEECH_S = 1.0  # from the first frame of speech to the last (esiaf/speech/speaker/quality.py)
log = logging.getLogger(__name__)
MAX_ENROL_S = 60.0  # of audio, at its own rate: what is converted and embedded is at most this long


class SpanEnrolment(BaseModel):
    """Every stored voice_id embedding of a stream whose span overlaps [start_ns, end_ns]."""
    model_config = ConfigDict(extra="forbid")
    stream: str
    start_ns: StrictInt = Field(ge=0, le=MAX_TIME_NS)
    end_ns: StrictInt = Field(ge=0, le=MAX_TIME_NS)
    encoder: Model | None = Field(None, description="the model of the voiceid that made the results "
                                  f"(default {DEFAULT_MODEL}; 512 floats: fused)")


class AnonymousEnrolment(BaseModel):
    """Every stored voice_id embedding of a stream labelled with an anonymous voice."""
    model_config = ConfigDict(extra="forbid")
    stream: str
    anonymous: str = Field(examples=["voice-2"])
    encoder: Model | None = Field(None, description="the model of the voiceid that made the results "
                                  f"(default {DEFAULT_MODEL}; 512 floats: fused)")


Component = Annotated[float, Field(ge=-1.0, le=1.0, allow_inf_nan=False)]  # of a unit-length embedding


class LearntEmbedding(BaseModel):
    """An utterance's embedding (256 floats) a voiceid identified as this voice with a margin."""
    model_config = ConfigDict(extra="forbid")
    encoder: Literal["ge2e", "dvector"]
    embedding: list[Component] = Field(min_length=SIZES["ge2e"], max_length=SIZES["ge2e"])


class LearntFused(BaseModel):
    """The same of the fused encoder (512 floats)."""
    model_config = ConfigDict(extra="forbid")
    encoder: Literal["fused"]
    embedding: list[Component] = Field(min_length=SIZES["fused"], max_length=SIZES["fused"])


ENROLMENT = TypeAdapter(SpanEnrolment | AnonymousEnrolment)
ENROLMENT_BODY = {"required": True, "content": {
    "application/json": {"schema": {"oneOf": [SpanEnrolment.model_json_schema(),
                                              AnonymousEnrolment.model_json_schema()]}},
    "multipart/form-data": {"schema": {"type": "object", "required": ["audio"], "properties": {
        "audio": {"type": "string", "format": "binary", "description": "a WAV of any rate"}}}}}}


def get_voices(request: Request, core: Orchestrator = Depends(get_core)) -> VoiceTable:
    table = getattr(request.app.state, "voices", None)
    if table is None:
        table = request.app.state.voices = VoiceTable(str(core.store.path))
    return table


def check_name(name: str) -> str:
    """A voice's name: the one rule for names ESIAF prints (esiaf/printable.py), no '/' or surrounding
    spaces, not an anonymous voice's ``voice-N`` nor ``unknown``."""
    problem = name_problem(name)
    if problem is not None:
        raise HTTPException(422, f"bad voice name {printable(name[:80])!r}: it {problem}")
    if "/" in name or name != name.strip():
        raise HTTPException(422, f"bad voice name {printable(name)!r}: it must be without '/' or surrounding spaces")
    if name.startswith("voice-"):
        raise HTTPException(422, f"bad voice name {printable(name)!r}: voice-N names are for anonymous voices")
    if name == "unknown":
        raise HTTPException(422, "bad voice name 'unknown': it is the voiceid's label for a segment it cannot tell")
    return name


@router.get("/voices", summary="enrolled voices (with ?embeddings=1, their embeddings; ETag for polling)",
            responses={304: {"description": "with ?embeddings=1: If-None-Match is the current ETag (with wait_s: "
                                            "it still was after waiting that long for a change)"}})
async def list_voices(request: Request, embeddings: bool = False,
                      wait_s: float = Query(0.0, ge=0.0, le=VOICES_MAX_WAIT_S, description=(
                          "with ?embeddings=1 and If-None-Match the current ETag: wait up to this long for a "
                          "change before answering 304 (a long poll)")),
                      encoder: Model | None = Query(None, description=(
                          "count (and with ?embeddings=1, give) only this encoder's embeddings; with "
                          f"?embeddings=1 it defaults to {MODELS[0]}, what a voiceid asked for before encoders "
                          "were named")),
                      core: Orchestrator = Depends(get_core), table: VoiceTable = Depends(get_voices)) -> Response:
    if embeddings and encoder is None:
        encoder = MODELS[0]
    changed = table.changed()  # taken before the ETag is read: a change between the two is not missed
    etag = await asyncio.to_thread(table.etag)
    seen = request.headers.get("if-none-match")
    if embeddings and seen == etag and wait_s > 0 and not core.closing.is_set():
        waits = [asyncio.ensure_future(changed.wait()), asyncio.ensure_future(core.closing.wait())]
        try:
            await asyncio.wait(waits, timeout=wait_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiting in waits:
                waiting.cancel()
        etag = await asyncio.to_thread(table.etag)
    if embeddings and seen == etag:
        return Response(status_code=304, headers={"ETag": etag})
    body = json.dumps({"voices": await asyncio.to_thread(table.listing, embeddings, encoder)})
    return Response(body, media_type="application/json", headers={"ETag": etag})


@router.delete("/voices/{name:path}", summary="forget a voice and every embedding of theirs",
               responses={404: {"model": Problem, "description": "no voice of that name"}})
async def delete_voice(name: str, table: VoiceTable = Depends(get_voices)) -> dict:
    if not await asyncio.to_thread(table.delete, name):
        raise HTTPException(404, f"no voice named {name!r}")
    table.notify()
    return {"deleted": name}


@router.post("/voices/{name}/learnt", summary="a voiceid's confidently identified utterance, learnt by that voice",
             responses={404: {"model": Problem, "description": "no voice of that name"}})
async def learn(name: str, body: Annotated[LearntEmbedding | LearntFused, Field(discriminator="encoder")],
                table: VoiceTable = Depends(get_voices)) -> dict:
    embedding = np.asarray(body.embedding, np.float32)
    try:
        dropped = await asyncio.to_thread(table.add, name, [embedding], LEARNT, body.encoder, True)
    except KeyError:
        raise HTTPException(404, f"no voice named {name!r}") from None
    table.notify()
    return {"name": name, "learnt": 1, "encoder": body.encoder, "dropped_oldest_learnt": dropped}


@router.post("/voices/{name}/forget-learnt", summary="delete the embeddings a voice learnt (its enrolment stays)",
             responses={404: {"model": Problem, "description": "no voice of that name"}})
async def forget_learnt(name: str, table: VoiceTable = Depends(get_voices)) -> dict:
    forgotten = await asyncio.to_thread(table.forget_learnt, name)
    if forgotten is None:
        raise HTTPException(404, f"no voice named {name!r}")
    if forgotten:
        table.notify()
    return {"name": name, "forgotten": forgotten}


@router.post("/voices/{name:path}", summary="add to a voice: multipart WAV field 'audio', or JSON naming a "
             "past utterance {stream, start_ns, end_ns} or an anonymous voice {stream, anonymous}",
             openapi_extra={"requestBody": ENROLMENT_BODY},
             responses={415: {"model": Problem, "description": "neither multipart nor JSON"},
                        409: {"model": Problem, "description": "a new voice beyond the most there may be (1,000)"}})
async def enrol_voice(name: str, request: Request, core: Orchestrator = Depends(get_core),
                      table: VoiceTable = Depends(get_voices)) -> dict:
    check_name(name)
    kind = request.headers.get("content-type", "")
    if kind.startswith("multipart/form-data"):
        form = await request.form()
        upload = form.get("audio")
        if upload is None or isinstance(upload, str):
            raise HTTPException(422, "no audio: send the WAV file as multipart field 'audio'")
        data = await upload.read()
        by_encoder, copies = await asyncio.to_thread(embed_wav, data, core.settings.enrolment_room_copies)
        source = "wav"
    elif kind.startswith("application/json"):
        try:
            body = ENROLMENT.validate_json(await request.body())
        except ValidationError as exc:
            raise HTTPException(422, "JSON enrolment needs {\"stream\", \"start_ns\", \"end_ns\"} (integers, "
                                     "start_ns <= end_ns) or {\"stream\", \"anonymous\"}: "
                                     + "; ".join(e["msg"] for e in exc.errors()[:3])) from None
        embeddings, source = stored_embeddings(core, body)
        by_encoder, copies = {encoder_of(body, embeddings): embeddings}, {}
    else:
        raise HTTPException(415, "no audio: send multipart field 'audio' (a WAV) or JSON {stream, start_ns, end_ns}")
    dropped = 0
    try:
        for encoder, embeddings in by_encoder.items():
            dropped = max(dropped, await asyncio.to_thread(table.add, name, embeddings, source, encoder,
                                                           False, copies.get(encoder, [])))
    except VoiceLimit as exc:
        raise HTTPException(409, str(exc)) from None
    except ValueError as exc:  # stored embeddings of an older orchestrator, taken unchecked
        raise HTTPException(422, f"cannot enrol: {exc}") from None
    finally:
        table.notify()
    return {"name": name, "added": len(next(iter(by_encoder.values()))), "source": source,
            "room_copies": len(next(iter(copies.values()), [])), "encoders": list(by_encoder),
            "dropped_oldest": dropped}


def encoder_of(body: SpanEnrolment | AnonymousEnrolment, embeddings: list[np.ndarray]) -> str:
    """The encoder that made a voiceid's stored embeddings: the body's, else fused for 512 floats, else
    the default model; 422 if their size is not that encoder's."""
    sizes = {e.size for e in embeddings}
    encoder = body.encoder or ("fused" if sizes == {SIZES["fused"]} else DEFAULT_MODEL)
    if sizes != {SIZES[encoder]}:
        raise HTTPException(422, f"cannot enrol: the stored embeddings have {sorted(sizes)} floats, "
                                 f"a {encoder} embedding {SIZES[encoder]} (name the voiceid's model as \"encoder\")")
    return encoder


def embed_wav(data: bytes, room_copies: int = 0) -> tuple[dict[str, list[np.ndarray]], dict[str, list[np.ndarray]]]:
    """The WAV's embedding by every encoder that loads here (fused when both do), and each encoder's
    embeddings of ``room_copies`` reverberant noisy copies of it (augment.room_copies; none without
    pyroomacoustics); 422 without enough speech. CPU work: run it off the event loop."""
    from esiaf.speech.speaker.encoders import fuse, shared_encoder
    from esiaf.speech.speaker.ge2e import EncoderError
    from esiaf.speech.speaker.quality import problem as speech_problem
    rate_hz, samples = read_wav(data, max_s=MAX_ENROL_S)  # rate, channels, length, finite: checked first
    samples = resample(samples, rate_hz, ENCODER_RATE_HZ)  # any rate is converted, not refused
    if samples.size < MIN_ENROL_SPEECH_S * ENCODER_RATE_HZ or float(np.max(np.abs(samples))) < 1e-3:
        raise HTTPException(422, f"audio has no speech to enrol: {samples.size / ENCODER_RATE_HZ:.2f} s, "
                                 f"at least {MIN_ENROL_SPEECH_S:.0f} s of speech needed")
    problem = speech_problem(samples, MIN_ENROL_SPEECH_S)
    if problem is not None:
        raise HTTPException(422, f"audio has no speech to enrol: {problem}")
    started = time.process_time()
    variants = [samples, *copies_of(samples, room_copies)]
    out: dict[str, list[np.ndarray]] = {}
    for model in ("ge2e", "dvector"):
        try:
            encoder = shared_encoder(model)
            out[model] = [encoder.embed(variant) for variant in variants]
        except EncoderError as exc:
            if model not in _unloadable:
                _unloadable.add(model)
                log.error("enrolment without the %s encoder: %s", model, exc)
    if not out:
        raise HTTPException(503, "no speaker encoder loads in the orchestrator: " + ", ".join(sorted(_unloadable)))
    if len(out) == 2:
        out["fused"] = [fuse(a, b) for a, b in zip(out["ge2e"], out["dvector"], strict=True)]
    log.info("enrolment embedded duration_s=%.2f room_copies=%d encoders=%s cpu_s=%.2f", samples.size /
             ENCODER_RATE_HZ, len(variants) - 1, ",".join(out), time.process_time() - started)
    return {model: e[:1] for model, e in out.items()}, {model: e[1:] for model, e in out.items()}


def copies_of(samples: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` room copies of the WAV's samples; none (said once in the log) without pyroomacoustics."""
    if count == 0:
        return []
    try:
        from esiaf.speech.speaker.augment import room_copies
        return room_copies(samples, count)
    except ImportError as exc:
        if not _no_rooms:
            _no_rooms.append(str(exc))
            log.error("WAV enrolment without room copies (enrolment_room_copies %d): %s; pip install "
                      "'esiaf[ssl]' installs pyroomacoustics", count, exc)
        return []


_unloadable: set[str] = set()  # encoders that failed to load here: said once in the log
_no_rooms: list[str] = []  # why room copies cannot be made here, once said in the log


def stored_embeddings(core: Orchestrator, body: SpanEnrolment | AnonymousEnrolment) -> tuple[list[np.ndarray], str]:
    stream = body.stream
    start_ns: int | None
    end_ns: int | None
    if isinstance(body, SpanEnrolment):
        anonymous = None
        start_ns, end_ns = body.start_ns, body.end_ns
        if start_ns > end_ns:
            raise HTTPException(422, "JSON enrolment needs integer \"start_ns\" <= \"end_ns\" (a capture span)")
        what = f"span {start_ns}..{end_ns} of stream {stream!r}"
    else:
        anonymous = body.anonymous
        start_ns = end_ns = None
        what = f"anonymous voice {anonymous!r} of stream {stream!r}"
    embeddings, after_id = [], None
    while True:
        page = core.store.query_results(type_name="voice_id", stream=stream, start_ns=start_ns, end_ns=end_ns,
                                        after_id=after_id, limit=500)
        for text in page.items:
            label = json.loads(text).get("voice_id") or {}
            if label.get("embedding") and (anonymous is None or label.get("label") == anonymous):
                embeddings.append(np.asarray(label["embedding"], np.float32))
        if len(page.items) < 500:
            break
        after_id = page.next_after_id
    if not embeddings:
        raise HTTPException(422, f"no speech to enrol: no voice_id result with an embedding in {what}")
    return embeddings, "anonymous" if anonymous else "span"

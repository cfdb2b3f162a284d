"""Request and response models of the REST API (they make the OpenAPI schema at /docs)."""
from __future__ import annotations

import json
import logging
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, field_validator, model_validator

from esiaf.results import KIND_PATTERN, RESULT_TYPES

from ..fusion.models import FusedResult, Result
from ..settings import FusionSettings

log = logging.getLogger(__name__)

SampleType = Literal["int8", "uint8", "int16", "uint16", "int24", "uint24", "int32", "uint32",
                     "float32", "float64"]
Kind = Annotated[str, Field(pattern=KIND_PATTERN, examples=[*RESULT_TYPES, "other"],
                            description="the result kind it produces (built in, or any name like 'rate'); "
                                        "other: none")]
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$"
MAX_INFO_BYTES = 64 * 1024  # a registration's info, as JSON
CURVE_KEY_PATTERN = r"^[0-9A-Za-z.\-:+=^!/*?&<>()\[\]{}@%$#]{40}$"  # a CURVE public key in Z85
# 1..65535, in the pattern so that the OpenAPI document says it too
PORT_PATTERN = r"(6553[0-5]|655[0-2][0-9]|65[0-4][0-9]{2}|6[0-4][0-9]{3}|[1-5][0-9]{4}|[1-9][0-9]{0,3})"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AudioFormat(Strict):
    sample_rate_hz: StrictInt = Field(gt=0, examples=[16000])
    sample_type: SampleType
    endianness: Literal["little", "big"] = "little"
    channels: StrictInt = Field(ge=1, description="samples are interleaved")


class TopicDeclaration(Strict):
    topic: str = Field(min_length=1, examples=["audio/raw"])
    format: AudioFormat = Field(description="the format this component wants (external format)")


_EXAMPLE_FORMAT: dict[str, Any] = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little",
                                    "channels": 1}


class RegisterRequest(Strict):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "name": "vad", "kind": "vad", "stream_id": "default",
        "inputs": [{"topic": "audio/raw", "format": _EXAMPLE_FORMAT}],
        "outputs": [{"topic": "vad/speech", "format": _EXAMPLE_FORMAT}],
        "audio_endpoint": "tcp://127.0.0.1:40123", "host": "robot-1", "pid": 4242, "info": {}}]})

    name: str = Field(min_length=1, max_length=64, pattern=NAME_PATTERN,
                      description="the component's name: its service. Several live instances of one "
                                  "name share the streams (each stream is served by one of them)")
    instance: str | None = Field(default=None, min_length=1, max_length=64, pattern=NAME_PATTERN,
                                 examples=["vad-5f3a9c01"],
                                 description="this instance's id (its component_id), unique among the live "
                                             "ones (409 if a live instance of another process holds it); "
                                             "default: one the orchestrator makes up")
    incarnation: str | None = Field(default=None, min_length=1, max_length=64,
                                    description="a token of the registering process: a registration with "
                                                "the instance id and incarnation of a live instance is "
                                                "that instance registering again (it replaces itself)")
    kind: Kind = Field(description="the result kind it produces; other: none. Its old name, `designation`, is "
                                   "accepted instead until the next release (logged as deprecated)")
    stream_id: str = Field(default="default", min_length=1)
    inputs: list[TopicDeclaration] = Field(default_factory=list)
    outputs: list[TopicDeclaration] = Field(default_factory=list)
    audio_endpoint: str | None = Field(
        default=None, max_length=300, pattern=rf"^tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]{{1,253}}):{PORT_PATTERN}$",
        examples=["tcp://127.0.0.1:40123"],
        description="where its XPUB socket is reached (tcp://HOST:PORT); null without outputs")
    audio_public_key: str | None = Field(
        default=None, pattern=CURVE_KEY_PATTERN, description="the Z85 CURVE public key of its audio output "
        "socket, with CURVE keys (esiaf keys): consumers connect with it")
    host: str = Field(default="", max_length=253)
    pid: StrictInt | None = None
    info: dict[str, Any] = Field(default_factory=dict, description=f"at most {MAX_INFO_BYTES} bytes as JSON")

    @field_validator("info")
    @classmethod
    def _info_bounded(cls, value: dict[str, Any]) -> dict[str, Any]:
        try:
            size = len(json.dumps(value, default=str))
        except (RecursionError, ValueError):
            raise ValueError("info is nested too deeply to store") from None
        if size > MAX_INFO_BYTES:
            raise ValueError(f"info is {size} bytes as JSON, more than {MAX_INFO_BYTES}")
        return value

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        """``designation``, the old name of ``kind``: accepted until the next release."""
        if isinstance(data, dict) and "designation" in data:
            data = dict(data)
            designation = data.pop("designation")
            if "kind" in data:
                raise ValueError("give kind only (designation is its old name)")
            data["kind"] = designation
            log.warning("event=deprecated field=designation name=%.64r: a registration says designation; its "
                        "name is kind (designation is accepted until the next release)", data.get("name"))
        return data

    @model_validator(mode="after")
    def _consistent(self) -> RegisterRequest:
        for side in ("inputs", "outputs"):
            topics = [d.topic for d in getattr(self, side)]
            repeated = sorted({t for t in topics if topics.count(t) > 1})
            if repeated:
                raise ValueError(f"{side} name a topic more than once: {', '.join(repeated)}")
        if self.outputs and not self.audio_endpoint:
            raise ValueError("audio_endpoint is required for a component with outputs")
        return self


class RegisterResponse(BaseModel):
    component_id: str = Field(examples=["vad-5f3a9c"])
    control_endpoint: str = Field(examples=["tcp://127.0.0.1:5560"])
    control_key: str = Field(description="this registration's control secret (a new one for every registration): "
                             "every control message must carry it as `control_key`, else it is refused")
    key_id: str = Field(description="names this registration: every result and end_of_stream notice carries it "
                        "with an HMAC-SHA256 keyed with `control_key` (docs/protocol.md, \"Results\"), else it is "
                        "refused")
    results_endpoint: str = Field(examples=["tcp://127.0.0.1:5561"])
    heartbeat_interval_s: float
    dead_after_s: float
    idle_heartbeat_interval_s: float = Field(description="the longest interval it may beat at while it has "
                                             "nothing to do (saying so in its heartbeats' `interval_s`)")
    peers: dict[str, list[str]] = Field(
        description="each input topic: the audio endpoints of its live producers")
    formats: dict[str, AudioFormat] = Field(
        description="each input and output topic: the format assigned to it (on the wire)")
    peer_keys: dict[str, str] = Field(default_factory=dict,
                                      description="each endpoint of peers: its producer's CURVE public key, "
                                                  "where it gave one")
    streams: list[str] | None = Field(default=None, description="one of several live instances of its "
                                      "service: the streams it serves (subscribe to those only); null: all")
    consumers: list[str] | None = Field(default=None, description="with outputs: the ids of the live components "
                                        "that take one of its output topics, the only subscribers its audio "
                                        "output may take; null without outputs")


class ComponentInfo(BaseModel):
    component_id: str
    name: str
    kind: Kind
    designation: Kind = Field(json_schema_extra={"deprecated": True},
                              description="the same as kind, its old name (until the next release)")
    stream_id: str
    status: Literal["alive", "dead", "replaced"]
    inputs: list[TopicDeclaration]
    outputs: list[TopicDeclaration]
    audio_endpoint: str | None
    audio_public_key: str | None
    host: str
    pid: int | None
    info: dict[str, Any]
    registered_ns: int
    last_seen_ns: int = Field(description="wall clock of its last message")
    departed_ns: int | None = Field(description="when it was declared dead or replaced")
    heartbeats: int
    results_received: int
    stats: dict[str, Any] | None = Field(description="the stats of its last heartbeat")
    heartbeat_interval_s: float | None = Field(default=None, description="the interval its last heartbeat said "
                                               "it beats at (longer while it is idle); null: none said")
    clock_offset_ms: float | None = Field(default=None, description="the orchestrator's clock minus the "
                                          "component's host's, from its heartbeats' round trips (null until "
                                          "measured); capture times it stamps are corrected by it")
    clock_uncertainty_ms: float | None = Field(default=None, description="how far clock_offset_ms may be off: "
                                               "half the shortest recent round trip")


class ServiceInfo(BaseModel):
    instances: list[str] = Field(description="the component_ids of its live instances, oldest first")
    serving: dict[str, str] = Field(description="each active stream and the instance serving it")


class ComponentList(BaseModel):
    items: list[ComponentInfo]
    services: dict[str, ServiceInfo] = Field(default_factory=dict, description="the live instances grouped "
                                             "by service (component name), and which serves each stream")


class TopicConsumer(BaseModel):
    component_id: str
    name: str
    format: AudioFormat = Field(description="the format it declared (external format)")
    converts: bool = Field(description="its declared format differs from the assigned one: its SDK "
                                       "converts (one conversion)")


class TopicProducer(TopicConsumer):
    audio_endpoint: str | None
    subscribers: int | None = Field(description="as the producer last reported; null if unknown")


class TopicInfo(BaseModel):
    topic: str
    format: AudioFormat = Field(description="assigned (internal) format: what travels on the wire")
    strategy: Literal["min_conversions", "min_bandwidth"] = Field(description="how it was chosen")
    bytes_per_second: int = Field(description="of one producer's audio in the assigned format")
    conversions: int = Field(description="how many producers and consumers convert to or from it")
    producers: list[TopicProducer]
    consumers: list[TopicConsumer]


class TopicList(BaseModel):
    items: list[TopicInfo]


NEXT_AFTER_ID = ("pass as after_id for the next page: the last item's id, or the after_id given "
                 "when the page is empty")


class ResultPage(BaseModel):
    items: list[Result]
    next_after_id: int | None = Field(description=NEXT_AFTER_ID)


class FusedPage(BaseModel):
    items: list[FusedResult]
    next_after_id: int | None = Field(description=NEXT_AFTER_ID)


class FusionList(BaseModel):
    items: list[FusionSettings]


class FusionStats(BaseModel):
    counters: dict[str, int] = Field(description="results, fused, completion_*, revisions, bad_*")
    open_fusions: int = Field(description="fusions waiting for components now")
    overhead_samples: int
    overhead_p50_ms: float | None = Field(
        description="completing result received -> fused result handed to websocket clients")
    overhead_p99_ms: float | None
    timed_out_samples: int
    timer_lateness_p50_ms: float | None = Field(
        description="timed-out fusions: deadline -> fused result handed to websocket clients")
    timer_lateness_p99_ms: float | None


class LatencyInfo(BaseModel):
    component: str
    count: int = Field(description="results received from it, ever")
    mean_ms: float = Field(description="running mean, as timeouts use it")
    p50_ms: float | None
    p95_ms: float | None
    timeout_ms: float = Field(description="how long a fusion waits for it after a window ends")


class LatencyList(BaseModel):
    items: list[LatencyInfo]


class Health(BaseModel):
    status: Literal["ok"]
    recovered: list[str] | None = Field(default=None, description="what --recover copied from a corrupt "
                                        "database at this start, a line each; absent when it was sound")


class Problem(BaseModel):
    detail: str

"""The control plane's messages, defined once for both ends (the SDK's heartbeat thread, esiaf/control.py,
and the orchestrator's ROUTER, esiaf_services/orchestrator/planes/control.py).

Each message is one JSON object in one ZeroMQ frame, told apart by its ``type``; here each is a pydantic
model and each direction a discriminated union on ``type``:

- component → orchestrator (DEALER → ROUTER): :class:`Heartbeat`;
- orchestrator → component: :class:`State`, :class:`Ack`, :class:`Unknown`, :class:`BeatNow`, and
  :class:`Command` (an order for one component, e.g. a player's: say, play, stop, barge-in);
- inside a component, its heartbeat thread → its data thread (an inproc PAIR socket): :class:`LocalState`,
  :class:`Fatal`, and the :class:`Command` as it came.

Why pydantic and JSON, not a protobuf ``oneof``: the bytes on the wire stay what they were (JSON, the same
fields), so an SDK and an orchestrator of different releases still understand each other; a heartbeat's
``stats`` are free-form JSON (an analyser's ``info``), which a proto message would carry as an opaque
string anyway; and the REST API beside it is pydantic too.

Every peer is untrusted. A message is at most :data:`MAX_MESSAGE_BYTES`; one that is not JSON, not an
object, of an unknown ``type`` or with a malformed required field raises :class:`MessageError` (the
receiver counts and logs it, and goes on). An optional field that is malformed reads as absent (``None``):
a heartbeat with a wrong ``state_version`` is still life and is answered with the full state, as one from
an SDK that sends none.
"""
from __future__ import annotations

from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    StrictFloat,
    StrictInt,
    Tag,
    TypeAdapter,
    ValidationError,
    WrapValidator,
)
from typing_extensions import TypedDict

__all__ = ["MAX_MESSAGE_BYTES", "MAX_PCM_BYTES", "Ack", "BargeIn", "BargeInPolicy", "BeatNow", "ClockReport",
           "Command", "Fatal", "Heartbeat", "LocalState", "MessageError", "Play", "PlayerOrder", "Say", "State",
           "StopPlaying", "ToComponent", "ToDataThread", "ToOrchestrator", "Unknown", "Unrecognised", "WireFormat",
           "encode", "parse_to_component", "parse_to_data_thread", "parse_to_orchestrator"]

MAX_MESSAGE_BYTES = 1 << 20  # a control message longer than this is refused unread (a heartbeat is ~1 KB)
MAX_TIME_NS = 2**62  # a time stamp beyond 2116 is not believed (sums of them never overflow int64)
MAX_CLOCK_OFFSET_NS = 366 * 86_400 * 10**9  # a clock further off than a year is not believed
MAX_NAME = 1024  # component ids, keys, endpoints, types: longer is not one of ours
# a Play order's PCM (16-bit mono at the player's rate): base64 in JSON, it stays under MAX_MESSAGE_BYTES
MAX_PCM_BYTES = 700_000  # 21.8 s at 16 kHz, 7.3 s at 48 kHz
MAX_TEXT = 2000  # a Say order's text

T = TypeVar("T")


def _or_none(value: Any, handler: Any) -> Any:
    try:
        return handler(value)
    except ValidationError:
        return None


# an optional field a peer may get wrong: a malformed value reads as absent, it does not refuse the message
Lenient = Annotated[T | None, WrapValidator(_or_none)]
Name = Annotated[str, Field(max_length=MAX_NAME)]
TimeNs = Annotated[StrictInt, Field(gt=-MAX_TIME_NS, lt=MAX_TIME_NS)]
Seconds = Annotated[StrictFloat, Field(allow_inf_nan=False)]  # an integer is a float too; a bool is not


class MessageError(ValueError):
    """A control message that is not one: not JSON, not an object, too long, of an unknown type, or a
    required field malformed. Its text says which, briefly (for a log line)."""


class Message(BaseModel):
    # a newer peer's extra fields are ignored; a message is a value
    model_config = ConfigDict(extra="ignore", frozen=True)


class WireFormat(TypedDict):
    """The format assigned to a topic: what travels on the wire (esiaf.formats.AudioFormat as a dict)."""

    sample_rate_hz: Annotated[StrictInt, Field(gt=0)]
    sample_type: Literal["int8", "uint8", "int16", "uint16", "int24", "uint24", "int32", "uint32",
                         "float32", "float64"]
    endianness: Literal["little", "big"]
    channels: Annotated[StrictInt, Field(ge=1)]


class ClockReport(Message):
    """A component's estimate of the orchestrator's clock against its own (esiaf/clock.py)."""

    offset_ns: Annotated[StrictInt, Field(ge=-MAX_CLOCK_OFFSET_NS, le=MAX_CLOCK_OFFSET_NS)] = Field(
        description="the orchestrator's clock minus the component's host's")
    uncertainty_ns: Annotated[StrictInt, Field(ge=0, le=MAX_CLOCK_OFFSET_NS)] = Field(
        description="how far the offset may be off: half the shortest recent round trip")


# component -> orchestrator

class Heartbeat(Message):
    """Sent every ``heartbeat_interval_s`` (every ``idle_heartbeat_interval_s`` while idle), at once when
    something it reports changed, and on every connection made again. Only one that carries the
    component's current ``control_key`` counts as life and is answered (:class:`State` or :class:`Ack`)."""

    type: Literal["heartbeat"] = "heartbeat"
    component_id: Lenient[Name] = Field(default=None, description="who sends it; absent: its routing id")
    control_key: Lenient[Name] = Field(default=None, description="its registration's control secret")
    stats: Lenient[dict[str, Any]] = Field(default=None, description="its inputs', outputs' and analyser's "
                                           "counters, free-form JSON (GET /components shows them)")
    sent_ns: Lenient[TimeNs] = Field(default=None, description="its clock when it sent this: echoed in the "
                                     "answer as echo_ns")
    clock: Lenient[ClockReport] = Field(default=None, description="its clock estimate; absent until it has one")
    state_version: Lenient[StrictInt] = Field(default=None, description="the version of the last state it "
                                              "applied (0: none since it registered)")
    interval_s: Lenient[Seconds] = Field(default=None, description="the interval until its next beat (longer "
                                         "while idle); absent: the fast one")


class Unrecognised(Message):
    """A message to the orchestrator of a type it does not know (a newer SDK's): proven by its key, it
    is life but nothing else, and is counted as bad."""

    type: Name
    component_id: Lenient[Name] = None
    control_key: Lenient[Name] = None


def _orchestrator_tag(value: Any) -> str | None:
    if isinstance(value, dict):
        return "heartbeat" if value.get("type") == "heartbeat" else "other"
    return "heartbeat" if isinstance(value, Heartbeat) else "other" if isinstance(value, Unrecognised) else None


ToOrchestrator = Annotated[Annotated[Heartbeat, Tag("heartbeat")] | Annotated[Unrecognised, Tag("other")],
                           Discriminator(_orchestrator_tag)]


# orchestrator -> component

class State(Message):
    """Everything a component must know, numbered: pushed when it changes, and the answer to a heartbeat
    whose ``state_version`` is not the current one."""

    type: Literal["state"] = "state"
    peers: dict[str, list[Name]] = Field(description="each input topic: the audio endpoints of its live "
                                         "producers")
    formats: dict[str, WireFormat] = Field(description="each input and output topic: its assigned format")
    peer_keys: Lenient[dict[str, Name]] = Field(default=None, description="with CURVE keys: each endpoint of "
                                                "peers, its producer's public key; absent without")
    streams: Lenient[list[Name]] = Field(default=None, description="one of several instances of its service: "
                                         "the streams it serves; absent: all")
    consumers: Lenient[list[Name]] = Field(default=None, description="with outputs: the component ids the "
                                           "orchestrator names as its consumers, the only subscribers its audio "
                                           "ports take; absent: none named yet")
    version: Lenient[StrictInt] = Field(default=None, description="this state's number (from 1, per "
                                        "registration); its heartbeats give it back once applied")
    echo_ns: Lenient[TimeNs] = Field(default=None, description="the answered heartbeat's sent_ns")
    orchestrator_ns: Lenient[TimeNs] = Field(default=None, description="the orchestrator's clock as it answered")


class Ack(Message):
    """The answer to a heartbeat whose state is current: life and a clock sample only."""

    type: Literal["ack"] = "ack"
    version: Lenient[StrictInt] = Field(default=None, description="the state version it has, still current")
    echo_ns: Lenient[TimeNs] = Field(default=None, description="the answered heartbeat's sent_ns")
    orchestrator_ns: Lenient[TimeNs] = Field(default=None, description="the orchestrator's clock as it answered")


class Unknown(Message):
    """The answer to a heartbeat naming a component the orchestrator does not know (it restarted, or
    declared it dead): register again."""

    type: Literal["unknown"] = "unknown"


class BeatNow(Message):
    """The connection the component's key last came on closed: beat now (from a newer connection), or be
    declared dead after ``disconnect_grace_s``."""

    type: Literal["beat_now"] = "beat_now"


# orders for one component (only a player takes these; any other logs and ignores them)

BargeInPolicy = Literal["stop", "duck", "ignore"]


class Say(Message):
    """Say ``text`` with the TTS ``voice`` (queued after what is already playing)."""

    action: Literal["say"] = "say"
    text: Annotated[str, Field(min_length=1, max_length=MAX_TEXT)]
    voice: Annotated[str, Field(max_length=64)] = "slt"


class Play(Message):
    """Play these samples (queued after what is already playing)."""

    model_config = ConfigDict(extra="ignore", frozen=True, ser_json_bytes="base64", val_json_bytes="base64")

    action: Literal["play"] = "play"
    name: Annotated[str, Field(max_length=256)] = Field(description="what to call it (playback results, GET "
                                                        "/streams/{stream}/playing)")
    pcm: Annotated[bytes, Field(max_length=MAX_PCM_BYTES)] = Field(
        description="16-bit little-endian mono PCM at the player's rate (base64 in JSON)")


class StopPlaying(Message):
    """Stop the item playing now and forget the queued ones."""

    action: Literal["stop"] = "stop"


class BargeIn(Message):
    """A person started speaking over the robot at ``capture_ns``: apply ``policy`` (stop: as StopPlaying;
    duck: play the rest of the current item lower; ignore: nothing)."""

    action: Literal["barge_in"] = "barge_in"
    policy: BargeInPolicy
    capture_ns: TimeNs


PlayerOrder = Annotated[Say | Play | StopPlaying | BargeIn, Field(discriminator="action")]


class Command(Message):
    """An order for the component, for one of its streams: sent to the connection its key last came on
    (dropped if none); its effect shows in what it reports (a player's playback results and heartbeat)."""

    type: Literal["command"] = "command"
    stream_id: Name
    order: PlayerOrder


ToComponent = Annotated[State | Ack | Unknown | BeatNow | Command, Field(discriminator="type")]


# inside a component: heartbeat thread -> data thread (inproc)

class LocalState(Message):
    """What the data thread connects to: the registration's state, after registering and at every new
    :class:`State`."""

    type: Literal["local_state"] = "local_state"
    component_id: str
    results_endpoint: str = Field(description="where results go (PUSH)")
    peers: dict[str, list[str]] = Field(description="each input topic: its producers' audio endpoints")
    formats: dict[str, WireFormat] = Field(description="each topic: its assigned format")
    peer_keys: dict[str, str] = Field(default_factory=dict, description="each peer endpoint: its CURVE key")
    streams: list[str] | None = Field(default=None, description="the streams it serves; None: all")
    consumers: list[str] | None = Field(default=None, description="the component ids its audio ports take")


class Fatal(Message):
    """The orchestrator will not have the component any more (or the heartbeat thread failed): stop."""

    type: Literal["fatal"] = "fatal"
    error: str = Field(description="why, one line")


ToDataThread = Annotated[LocalState | Fatal | Command, Field(discriminator="type")]

_TO_ORCHESTRATOR: TypeAdapter[Heartbeat | Unrecognised] = TypeAdapter(ToOrchestrator)
_TO_COMPONENT: TypeAdapter[State | Ack | Unknown | BeatNow | Command] = TypeAdapter(ToComponent)
_TO_DATA_THREAD: TypeAdapter[LocalState | Fatal | Command] = TypeAdapter(ToDataThread)


def _parse(adapter: TypeAdapter[Any], data: bytes) -> Any:
    if len(data) > MAX_MESSAGE_BYTES:
        raise MessageError(f"{len(data)} bytes, more than {MAX_MESSAGE_BYTES}")
    try:
        return adapter.validate_json(data)
    except ValidationError as exc:
        first = exc.errors(include_url=False, include_context=False, include_input=False)[0]
        where = ".".join(str(part) for part in first["loc"])
        raise MessageError(f"{where + ': ' if where else ''}{first['msg']}"[:200]) from None


def parse_to_orchestrator(data: bytes) -> Heartbeat | Unrecognised:
    """A message a component sent the orchestrator; raises :class:`MessageError`."""
    return _parse(_TO_ORCHESTRATOR, data)  # type: ignore[no-any-return]


def parse_to_component(data: bytes) -> State | Ack | Unknown | BeatNow | Command:
    """A message the orchestrator sent a component; raises :class:`MessageError`."""
    return _parse(_TO_COMPONENT, data)  # type: ignore[no-any-return]


def parse_to_data_thread(data: bytes) -> LocalState | Fatal | Command:
    """A message a component's heartbeat thread handed its data thread; raises :class:`MessageError`."""
    return _parse(_TO_DATA_THREAD, data)  # type: ignore[no-any-return]


def encode(message: Message) -> bytes:
    """The message as the JSON frame that travels; absent optional fields are left out."""
    return message.__pydantic_serializer__.to_json(message, exclude_none=True)

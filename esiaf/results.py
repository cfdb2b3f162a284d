"""Building result messages from plain Python values."""
from __future__ import annotations

import re
import time
from collections.abc import Mapping, Sequence
from typing import Any

from esiaf.proto import esiaf_pb2 as pb

# The one source of truth for the built-in kinds: the payload fields of Result in proto/esiaf.proto
# (all but "nothing" and "generic"), each with its RESULT_TYPE_<NAME>. Every other kind is data:
# RESULT_TYPE_GENERIC, Result.kind naming it, a GenericResult payload.
_PAYLOAD_FIELDS = [f.name for f in pb.Result.DESCRIPTOR.oneofs_by_name["payload"].fields]
RESULT_TYPES = tuple(name for name in _PAYLOAD_FIELDS if name not in ("nothing", "generic"))
DESIGNATIONS = (*RESULT_TYPES, "other")
PB_RESULT_TYPE = {name: pb.ResultType.Value(f"RESULT_TYPE_{name.upper()}") for name in RESULT_TYPES}
RESULT_TYPE_NAME = {value: name for name, value in PB_RESULT_TYPE.items()}
KIND_PATTERN = r"^[a-z][a-z0-9_]{0,39}$"  # any kind's name: "rate", "duration", "voice_id"
LABEL_PAYLOADS = tuple(f.name for f in pb.Result.DESCRIPTOR.oneofs_by_name["payload"].fields
                       if f.message_type is pb.LabelResult.DESCRIPTOR)  # emotion, gender, voice_id


def valid_kind(name: str) -> bool:
    return isinstance(name, str) and re.match(KIND_PATTERN, name) is not None and name != "other"


def kind_of(result: pb.Result) -> str:
    """The kind of a result: a built-in payload's name, or what a generic result names."""
    return result.kind if result.type == pb.RESULT_TYPE_GENERIC else RESULT_TYPE_NAME.get(result.type, "")


def generic(label: str = "", probability: float = 0.0, class_probabilities: Mapping[str, float] | None = None,
            value: float | None = None, text: str = "", attributes: Mapping[str, Any] | None = None
            ) -> pb.GenericResult:
    """The payload of a kind that is not built in: a label, a number, a text, JSON-able attributes."""
    payload = pb.GenericResult(label=label, probability=probability, text=text,
                               class_probabilities=dict(class_probabilities or {}))
    if value is not None:
        payload.value, payload.has_value = float(value), True
    if attributes:
        payload.attributes.update(dict(attributes))
    return payload


# Events: kinds of their own, not built into the proto, that the SDK defines for every service and the
# orchestrator understands (docs/protocol.md, "Results"); they say nothing of the audio's coverage.
SPEECH_START = "speech_start"  # a vad opened a segment: span = (speech start, the capture time it decided)
PLAYBACK = "playback"  # a player plays an item: span = when it plays (revised by a later one if stopped early)
ECHO = "echo"  # the echo canceller's output while it cancels: span = a block of it (esiaf_services/aec/evidence.py)


def speech_start(probability: float) -> pb.GenericResult:
    """The payload of a ``speech_start`` event: the speech probability when the segment opened."""
    return generic(probability=min(1.0, max(0.0, float(probability))))


def playback(name: str, item: int, stopped: bool, part: int = 0) -> pb.GenericResult:
    """The payload of a ``playback`` event: what plays (``text``), its number at the player, the part of it
    (a stretch that sounds), and whether this report is the part's real end after a stop (it then revises
    the part's first report)."""
    return generic(text=name[:200], attributes={"item": item, "part": part, "stopped": stopped})


def echo(level_db: float, above_floor_db: float | None, cancelled_db: float, converged: bool) -> pb.GenericResult:
    """The payload of an ``echo`` event: the canceller's output level in the block (dB, 96 = full scale), how
    far it stands above the output's floor (absent until the floor is known), how much the canceller took off
    (the microphones' level minus the output's), and whether the canceller had converged."""
    attributes: dict[str, Any] = {"converged": converged, "cancelled_db": cancelled_db}
    if above_floor_db is not None:
        attributes["above_floor_db"] = above_floor_db
    return generic(value=level_db, attributes=attributes)


def hypothesis(text: str, probability: float, words: Sequence[Mapping[str, Any]] = ()) -> pb.Hypothesis:
    return pb.Hypothesis(text=text, probability=probability, words=[pb.WordTiming(**w) for w in words])


def ssl_direction(azimuth_deg: float, elevation_deg: float = 0.0, probability: float = 1.0,
                  source_id: str = "") -> pb.SslDirection:
    return pb.SslDirection(source_id=source_id, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
                           probability=probability)


def make_result(component: str, kind: str, stream_id: str, span: tuple[int, int], sequence: int,
                **payload: Any) -> pb.Result:
    """One Result of kind ``kind``. ``payload`` holds exactly one of: the built-in kind's
    payload (vad=, speech=, ssl=, emotion=, gender=, voice_id=: a message or a dict of its
    fields); for any other kind, generic= (or the kind's own name) with a GenericResult or the
    keyword arguments of :func:`generic`; or nothing= (a reason string): "covered, no result"."""
    built_in = kind in PB_RESULT_TYPE
    if not built_in and not valid_kind(kind):
        raise ValueError(f"bad result kind {kind!r}: a name like 'rate' ({KIND_PATTERN})")
    allowed = (kind, "nothing") if built_in else (kind, "generic", "nothing")
    if len(payload) != 1 or next(iter(payload)) not in allowed:
        raise ValueError(f"a {kind} result needs exactly one payload of {', '.join(allowed)}, "
                         f"got {list(payload)}")
    start_ns, end_ns = span
    if end_ns < start_ns:
        raise ValueError(f"result span ends before it starts: {start_ns} > {end_ns}")
    result = pb.Result(component=component, type=PB_RESULT_TYPE.get(kind, pb.RESULT_TYPE_GENERIC),
                       stream_id=stream_id, span=pb.Span(start_ns=start_ns, end_ns=end_ns),
                       produced_ns=time.time_ns(), sequence=sequence, kind="" if built_in else kind)
    (key, value), = payload.items()
    if not built_in and key != "nothing":
        result.generic.CopyFrom(value if isinstance(value, pb.GenericResult) else generic(**value))
    elif key == "nothing":
        result.nothing.reason = str(value)
    elif isinstance(value, Mapping):
        getattr(result, key).CopyFrom(_message_for(key)(**value))
    else:
        getattr(result, key).CopyFrom(value)
    return result


def _message_for(key: str) -> type:
    return {"vad": pb.VadResult, "speech": pb.SpeechResult, "ssl": pb.SslResult}.get(key, pb.LabelResult)

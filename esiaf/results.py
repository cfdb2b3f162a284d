"""Building result messages from plain Python values."""
from __future__ import annotations

import time
from typing import Any, Mapping, Sequence

from esiaf.proto import esiaf_pb2 as pb

RESULT_TYPES = ("vad", "speech", "ssl", "emotion", "gender", "voice_id")
DESIGNATIONS = RESULT_TYPES + ("other",)
PB_RESULT_TYPE = {name: getattr(pb, f"RESULT_TYPE_{name.upper()}") for name in RESULT_TYPES}
RESULT_TYPE_NAME = {value: name for name, value in PB_RESULT_TYPE.items()}


def hypothesis(text: str, probability: float, words: Sequence[Mapping[str, Any]] = ()) -> pb.Hypothesis:
    return pb.Hypothesis(text=text, probability=probability, words=[pb.WordTiming(**w) for w in words])


def ssl_direction(azimuth_deg: float, elevation_deg: float = 0.0, probability: float = 1.0,
                  source_id: str = "") -> pb.SslDirection:
    return pb.SslDirection(source_id=source_id, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
                           probability=probability)


def make_result(component: str, result_type: str, stream_id: str, span: tuple[int, int], sequence: int,
                **payload: Any) -> pb.Result:
    """One Result. ``payload`` holds exactly one of vad=, speech=, ssl=, emotion=, gender=, voice_id=
    (a message or a dict of its fields) or nothing= (a reason string): "covered, no result"."""
    if result_type not in PB_RESULT_TYPE:
        raise ValueError(f"unknown result type {result_type!r}; known: {', '.join(RESULT_TYPES)}")
    if len(payload) != 1 or next(iter(payload)) not in RESULT_TYPES + ("nothing",):
        raise ValueError(f"a result needs exactly one payload of {RESULT_TYPES + ('nothing',)}, got {list(payload)}")
    start_ns, end_ns = span
    if end_ns < start_ns:
        raise ValueError(f"result span ends before it starts: {start_ns} > {end_ns}")
    result = pb.Result(component=component, type=PB_RESULT_TYPE[result_type], stream_id=stream_id,
                       span=pb.Span(start_ns=start_ns, end_ns=end_ns), produced_ns=time.time_ns(),
                       sequence=sequence)
    (key, value), = payload.items()
    if key == "nothing":
        result.nothing.reason = str(value)
    elif isinstance(value, Mapping):
        getattr(result, key).CopyFrom(_message_for(key)(**value))
    else:
        getattr(result, key).CopyFrom(value)
    return result


def _message_for(key: str) -> type:
    return {"vad": pb.VadResult, "speech": pb.SpeechResult, "ssl": pb.SslResult}.get(key, pb.LabelResult)

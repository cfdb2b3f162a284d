"""What a result must be for the orchestrator to store it (docs/reliability.md, "Limits"): checked
by the orchestrator on arrival (esiaf_services/orchestrator/planes/codec.py) and by the SDK before
it sends one (esiaf/node.py), so an analyser that produces a result the orchestrator would refuse
learns it at once: counted, logged, in its heartbeat (``results_invalid``), never sent.
"""
from __future__ import annotations

import math

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from esiaf.printable import MAX_NAME_CHARS  # component and stream names
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import PB_RESULT_TYPE, kind_of, valid_kind

NO_RESULT = "nothing"

# Bounds on what a peer may send (docs/reliability.md).
MAX_RESULT_BYTES = 256 * 1024  # one encoded Result
MAX_SPAN_NS = 24 * 3600 * 10**9  # one result covers at most a day of audio
MAX_STREAM_DISTANCE_NS = 30 * 24 * 3600 * 10**9  # spans within 30 days of their stream's first one
MAX_TIME_NS = 2**62  # 2116: sums of capture times never overflow int64
MAX_STRING_CHARS = 10_000
MAX_REPEATED = 1_000
PROBABILITY_FIELDS = {"probability", "class_probabilities"}


class BadResult(ValueError):
    """A result that cannot be stored: the message says why."""


def check_values(message: Message, where: str) -> None:
    """Every float finite, probabilities in [0, 1], strings and lists bounded; BadResult if not."""
    for field, value in message.ListFields():
        name = f"{where}.{field.name}"
        is_map = field.message_type is not None and field.message_type.GetOptions().map_entry
        if is_map:
            values = list(value.values())
            value_field = field.message_type.fields_by_name["value"]
            if any(len(key) > MAX_STRING_CHARS for key in value):
                raise BadResult(f"{name} has a key longer than {MAX_STRING_CHARS} characters")
        else:
            values, value_field = (list(value) if field.is_repeated else [value]), field
        if len(values) > MAX_REPEATED:
            raise BadResult(f"{name} has {len(values)} entries, more than {MAX_REPEATED}")
        for item in values:
            if value_field.type == FieldDescriptor.TYPE_MESSAGE:
                check_values(item, name)
            elif value_field.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
                if not math.isfinite(item):
                    raise BadResult(f"{name} is not a finite number ({item})")
                if field.name in PROBABILITY_FIELDS and not 0.0 <= item <= 1.0:
                    raise BadResult(f"{name} is {item}, not a probability in [0, 1]")
            elif value_field.type == FieldDescriptor.TYPE_STRING and len(item) > MAX_STRING_CHARS:
                raise BadResult(f"{name} is longer than {MAX_STRING_CHARS} characters")


def check_span(start_ns: int, end_ns: int, reference_ns: int | None, what: str) -> None:
    """A span that is ordered, at most a day long, before 2116 (no overflow in sums) and, given
    the stream's reference time (its first span), within 30 days of it."""
    if end_ns < start_ns:
        raise BadResult(f"{what} ends before it starts ({start_ns} > {end_ns})")
    if start_ns < 0 or end_ns >= MAX_TIME_NS:
        raise BadResult(f"{what} span {start_ns}..{end_ns} is outside 1970..2116")
    if end_ns - start_ns > MAX_SPAN_NS:
        raise BadResult(f"{what} spans {(end_ns - start_ns) / 1e9:.0f} s, more than a day")
    if reference_ns is not None and max(abs(start_ns - reference_ns), abs(end_ns - reference_ns)) \
            > MAX_STREAM_DISTANCE_NS:
        raise BadResult(f"{what} span {start_ns}..{end_ns} is more than 30 days from the stream's "
                        f"first result ({reference_ns})")


def check_result(result: pb.Result, reference_ns: int | None = None) -> None:
    """Raises :class:`BadResult` saying why, if the orchestrator would refuse ``result`` (decoded):
    its kind and payload, its names, its span (near ``reference_ns``, its stream's first span, if
    known) and every value in it. Its encoded size is the caller's to check (MAX_RESULT_BYTES)."""
    type_name = kind_of(result)
    if result.type == pb.RESULT_TYPE_GENERIC and (not valid_kind(type_name) or type_name in PB_RESULT_TYPE):
        raise BadResult(f"generic result from {result.component!r} has no valid kind ({result.kind[:50]!r})")
    if not type_name:
        raise BadResult(f"result from {result.component!r} has no valid type ({result.type})")
    payload = result.WhichOneof("payload")
    if payload is None:
        raise BadResult(f"{type_name} result from {result.component!r} has no payload")
    expected = "generic" if result.type == pb.RESULT_TYPE_GENERIC else type_name
    if payload not in (expected, NO_RESULT):
        raise BadResult(f"{type_name} result from {result.component!r} carries a {payload} payload")
    if not result.component:
        raise BadResult(f"{type_name} result without a component name")
    if len(result.component) > MAX_NAME_CHARS or len(result.stream_id) > MAX_NAME_CHARS:
        raise BadResult(f"{type_name} result with a component or stream name over {MAX_NAME_CHARS} characters")
    check_span(result.span.start_ns, result.span.end_ns, reference_ns,
               f"{type_name} result from {result.component!r}")
    check_values(result, type_name)

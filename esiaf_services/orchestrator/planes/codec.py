"""Result protobufs as the JSON of docs/protocol.md (integers stay integers)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from google.protobuf import json_format
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, Message
from google.protobuf.struct_pb2 import Struct

from esiaf.proto import esiaf_pb2 as pb
from esiaf.result_checks import (  # the bounds: the SDK checks them before sending
    MAX_RESULT_BYTES,
    BadResult,
    check_result,
)
from esiaf.results import PB_RESULT_TYPE, kind_of

# ResultType enum value -> the name used in JSON, kinds and settings (from the proto).
TYPE_NAMES = {value: name for name, value in PB_RESULT_TYPE.items()}
NO_RESULT = "nothing"


def _value(field: FieldDescriptor, value: Any) -> Any:
    if field.message_type is Struct.DESCRIPTOR:  # a generic result's attributes: plain JSON
        return json_format.MessageToDict(value)
    if field.type == FieldDescriptor.TYPE_MESSAGE:
        return message_to_dict(value)
    if field.type == FieldDescriptor.TYPE_ENUM:
        known = field.enum_type.values_by_number.get(value)
        return known.name if known is not None else value
    if field.type == FieldDescriptor.TYPE_BYTES:
        return value.hex()
    return value


def message_to_dict(message: Message) -> dict[str, Any]:
    """Every field (defaults included) by its proto name; int64 stay ints, unlike MessageToJson."""
    out: dict[str, Any] = {}
    for field in message.DESCRIPTOR.fields:
        if field.containing_oneof is not None and not message.HasField(field.name):
            continue
        value = getattr(message, field.name)
        if field.message_type is not None and field.message_type.GetOptions().map_entry:
            value_field = field.message_type.fields_by_name["value"]
            out[field.name] = {k: _value(value_field, v) for k, v in value.items()}
        elif field.is_repeated:
            out[field.name] = [_value(field, v) for v in value]
        else:
            out[field.name] = _value(field, value)
    return out


def parse_result(data: bytes, reference_ns: Callable[[str], int | None] = lambda stream_id: None) -> pb.Result:
    """Decodes and checks one Result (esiaf/result_checks.py); raises :class:`BadResult`.
    ``reference_ns(stream_id)`` is the time its span must lie near (see :func:`check_span`), if known."""
    if len(data) > MAX_RESULT_BYTES:
        raise BadResult(f"result of {len(data)} bytes, more than {MAX_RESULT_BYTES}")
    result = pb.Result()
    try:
        result.ParseFromString(data)
    except (DecodeError, RecursionError, ValueError) as exc:
        raise BadResult(f"not a Result protobuf ({len(data)} bytes): {exc}") from None
    check_result(result, reference_ns(result.stream_id))
    return result


def type_name(result: pb.Result) -> str:
    return kind_of(result)


def result_to_json(result: pb.Result, result_id: int, received_ns: int, capture_offset_ns: int = 0) -> dict[str, Any]:
    """The JSON of one stored result, as in docs/protocol.md; its latency on our clock, the capture
    times' corrected by ``capture_offset_ns`` (ours minus the capturing host's)."""
    payload = result.WhichOneof("payload")
    return {
        "id": result_id,
        "component": result.component,
        "instance": result.instance,
        "type": kind_of(result),
        "stream_id": result.stream_id,
        "span": {"start_ns": result.span.start_ns, "end_ns": result.span.end_ns},
        "produced_ns": result.produced_ns,
        "received_ns": received_ns,
        "latency_ms": round((received_ns - result.span.end_ns - capture_offset_ns) / 1e6, 3),
        "sequence": result.sequence,
        # a generic payload is keyed by its kind, like the built-in ones: {"type": "rate", "rate": {...}}
        (kind_of(result) if payload == "generic" else payload): message_to_dict(getattr(result, payload)),
    }

"""Result protobufs as the JSON of docs/protocol.md (integers stay integers)."""
from __future__ import annotations

from typing import Any

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, Message

from esiaf.proto import esiaf_pb2 as pb

# ResultType enum value -> the name used in JSON, designations and settings.
TYPE_NAMES = {
    pb.RESULT_TYPE_VAD: "vad",
    pb.RESULT_TYPE_SPEECH: "speech",
    pb.RESULT_TYPE_SSL: "ssl",
    pb.RESULT_TYPE_EMOTION: "emotion",
    pb.RESULT_TYPE_GENDER: "gender",
    pb.RESULT_TYPE_VOICE_ID: "voice_id",
}
NO_RESULT = "nothing"


class BadResult(ValueError):
    """A result that cannot be stored: the message says why."""


def _value(field: FieldDescriptor, value: Any) -> Any:
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


def parse_result(data: bytes) -> pb.Result:
    """Decodes and checks one Result; raises :class:`BadResult`."""
    result = pb.Result()
    try:
        result.ParseFromString(data)
    except DecodeError as exc:
        raise BadResult(f"not a Result protobuf ({len(data)} bytes): {exc}") from None
    type_name = TYPE_NAMES.get(result.type)
    if type_name is None:
        raise BadResult(f"result from {result.component!r} has no valid type ({result.type})")
    payload = result.WhichOneof("payload")
    if payload is None:
        raise BadResult(f"{type_name} result from {result.component!r} has no payload")
    if payload not in (type_name, NO_RESULT):
        raise BadResult(f"{type_name} result from {result.component!r} carries a {payload} payload")
    if not result.component:
        raise BadResult(f"{type_name} result without a component name")
    if result.span.end_ns < result.span.start_ns:
        raise BadResult(f"{type_name} result from {result.component!r} ends before it starts "
                        f"({result.span.start_ns} > {result.span.end_ns})")
    return result


def type_name(result: pb.Result) -> str:
    return TYPE_NAMES[result.type]


def result_to_json(result: pb.Result, result_id: int, received_ns: int) -> dict[str, Any]:
    """The JSON of one stored result, as in docs/protocol.md."""
    payload = result.WhichOneof("payload")
    return {
        "id": result_id,
        "component": result.component,
        "type": TYPE_NAMES[result.type],
        "stream_id": result.stream_id,
        "span": {"start_ns": result.span.start_ns, "end_ns": result.span.end_ns},
        "produced_ns": result.produced_ns,
        "received_ns": received_ns,
        "latency_ms": round((received_ns - result.span.end_ns) / 1e6, 3),
        "sequence": result.sequence,
        payload: message_to_dict(getattr(result, payload)),
    }

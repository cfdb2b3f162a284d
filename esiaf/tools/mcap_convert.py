"""The orchestrator's JSON (docs/protocol.md: results, fused results, partials) as ESIAF's protobufs,
so that a recording holds one schema per channel (proto/esiaf.proto) and the ``mcap`` tools and
Foxglove decode it. What the protobufs have no field for (ids of stored results, latencies) is left out."""
from __future__ import annotations

from typing import Any

from google.protobuf import json_format

from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import PB_RESULT_TYPE

PAYLOADS = {field.name for field in pb.Result.DESCRIPTOR.oneofs_by_name["payload"].fields}
COMPLETIONS = {"complete": pb.COMPLETION_COMPLETE, "timed_out": pb.COMPLETION_TIMED_OUT,
               "components_gone": pb.COMPLETION_COMPONENTS_GONE}
MISSING_REASONS = {"timed_out": pb.MISSING_REASON_TIMED_OUT, "gone": pb.MISSING_REASON_GONE}


def _span(value: Any) -> pb.Span:
    value = value if isinstance(value, dict) else {}
    return pb.Span(start_ns=int(value.get("start_ns") or 0), end_ns=int(value.get("end_ns") or 0))


def _result_type(kind: str) -> Any:  # a ResultType value (the stubs type enum values as their class)
    return PB_RESULT_TYPE.get(kind, pb.RESULT_TYPE_GENERIC)


def result_from_json(value: dict[str, Any]) -> pb.Result:
    """One stored result (``GET /results``, a fused result's anchor and results) as a Result."""
    kind = str(value.get("type") or "")
    result = pb.Result(component=str(value.get("component") or ""), instance=str(value.get("instance") or ""),
                       type=_result_type(kind), stream_id=str(value.get("stream_id") or ""),
                       span=_span(value.get("span")), produced_ns=int(value.get("produced_ns") or 0),
                       sequence=int(value.get("sequence") or 0), kind="" if kind in PB_RESULT_TYPE else kind)
    if isinstance(value.get("nothing"), dict):
        result.nothing.reason = str(value["nothing"].get("reason", ""))
    elif kind in PB_RESULT_TYPE and isinstance(value.get(kind), dict):
        json_format.ParseDict(value[kind], getattr(result, kind), ignore_unknown_fields=True)
    elif isinstance(value.get(kind), dict):  # a generic payload is keyed by its kind
        json_format.ParseDict(value[kind], result.generic, ignore_unknown_fields=True)
    return result


def partial_from_json(value: dict[str, Any]) -> pb.Result:
    """A ``partial`` websocket event as the generic result the recogniser sent (kind ``partial``; its
    ``stable`` prefix and ``closed`` in the attributes)."""
    result = pb.Result(component=str(value.get("component") or ""), instance=str(value.get("instance") or ""),
                       type=pb.RESULT_TYPE_GENERIC, kind="partial", stream_id=str(value.get("stream_id") or ""),
                       span=_span(value.get("span")), produced_ns=int(value.get("received_ns") or 0))
    result.generic.text = str(value.get("text") or "")
    result.generic.probability = float(value.get("probability") or 0.0)
    result.generic.attributes.update({"stable": str(value.get("stable") or ""), "closed": bool(value.get("closed"))})
    return result


def fused_from_json(value: dict[str, Any]) -> pb.FusedResult:
    """A fused result (``GET /fused``, the websocket's ``fused_result``) as a FusedResult."""
    fused = pb.FusedResult(id=int(value.get("id") or 0), revision=int(value.get("revision") or 0),
                           fusion=str(value.get("fusion") or ""), stream_id=str(value.get("stream_id") or ""),
                           completion=COMPLETIONS.get(str(value.get("completion")), pb.COMPLETION_UNSPECIFIED),
                           missing_components=[str(name) for name in value.get("missing_components") or []],
                           published_ns=int(value.get("published_ns") or 0), seq=int(value.get("seq") or 0))
    if isinstance(value.get("anchor"), dict):
        fused.anchor.CopyFrom(result_from_json(value["anchor"]))
    results = value.get("results") or {}
    for items in results.values() if isinstance(results, dict) else []:
        fused.results.extend(result_from_json(item) for item in items if isinstance(item, dict))
    for missing in value.get("missing") or []:
        kind = str(missing.get("type") or "")
        fused.missing.add(component=str(missing.get("component") or ""), type=_result_type(kind),
                          reason=MISSING_REASONS.get(str(missing.get("reason")), pb.MISSING_REASON_UNSPECIFIED))
    for kind, aggregate in (value.get("aggregates") or {}).items():
        if kind in pb.Aggregates.DESCRIPTOR.fields_by_name and isinstance(aggregate, dict):
            json_format.ParseDict(aggregate, getattr(fused.aggregates, kind), ignore_unknown_fields=True)
    return fused

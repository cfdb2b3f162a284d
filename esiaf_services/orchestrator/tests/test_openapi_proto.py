"""The API's documented result models (/docs, /openapi.json) against the proto they are made from:
every field the codec sends (esiaf_services/orchestrator/planes/codec.py sends every proto field of a
payload) must be in the OpenAPI document, and nothing the proto lacks may be documented as sent."""
from __future__ import annotations

import pytest

from esiaf.proto import esiaf_pb2 as pb
from esiaf_services.orchestrator.api.app import create_app
from esiaf_services.orchestrator.planes.codec import result_to_json
from esiaf_services.orchestrator.settings import OrchestratorSettings

# proto message -> the OpenAPI schema documenting its JSON
PAIRS = {
    pb.Span: "Span",
    pb.VadResult: "VadPayload",
    pb.WordTiming: "WordTiming",
    pb.Hypothesis: "Hypothesis",
    pb.SpeechResult: "SpeechPayload",
    pb.SslDirection: "SslDirection",
    pb.SslResult: "SslPayload",
    pb.LabelResult: "LabelPayload",
    pb.UtteranceQuality: "UtteranceQuality",
    pb.NoResult: "NoResultPayload",
}
# Result's own fields that the JSON gives under another name or shape (codec.result_to_json)
RESULT_RENAMED = {"type": "type", "kind": "type", "payload": None}  # kind and type become one "type" string
RESULT_ADDED = {"id", "received_ns", "latency_ms"}  # the orchestrator's, not the component's


@pytest.fixture(scope="module")
def schemas() -> dict:
    return create_app(OrchestratorSettings(token="t")).openapi()["components"]["schemas"]


def properties(schemas: dict, name: str) -> set[str]:
    return set(schemas[name]["properties"])


@pytest.mark.parametrize("message, schema", PAIRS.items(), ids=list(PAIRS.values()))
def test_a_payload_is_documented_field_for_field(schemas, message, schema):
    assert properties(schemas, schema) == {f.name for f in message.DESCRIPTOR.fields}


def test_a_result_is_documented_field_for_field(schemas):
    oneof = {f.name for f in pb.Result.DESCRIPTOR.oneofs_by_name["payload"].fields} - {"generic"}
    own = {f.name for f in pb.Result.DESCRIPTOR.fields if f.containing_oneof is None}
    expected = {RESULT_RENAMED.get(name, name) for name in own} | oneof | RESULT_ADDED
    assert properties(schemas, "Result") == expected


@pytest.mark.parametrize("payload", ["vad", "speech", "ssl", "emotion", "voice_id", "nothing"])
def test_what_the_codec_sends_is_what_is_documented(schemas, payload):
    """A result with every field set, through the codec: each key it sends, at every level, is in
    the schema of that level."""
    result = pb.Result(component="c", type=pb.RESULT_TYPE_VAD, stream_id="s", produced_ns=1, sequence=1)
    result.span.start_ns, result.span.end_ns = 1, 2
    if payload == "vad":
        result.vad.probability = 0.5
    elif payload == "speech":
        h = result.speech.hypotheses.add(text="a", probability=0.5, raw_text="a", match_score=1.0, out_of_set=False,
                                         logprob=-3.0, raw_logprob=-2.5, margin=4.0)
        h.words.add(word="a", start_ns=1, end_ns=2, probability=0.5)
    elif payload == "ssl":
        result.ssl.directions.add(source_id="1", azimuth_deg=10, elevation_deg=0, probability=0.5,
                                  elevation_known=True, track_azimuth_deg=11, background=False)
        result.ssl.algorithm, result.ssl.level_db = "NormMUSIC", 60.0
    elif payload == "nothing":
        result.nothing.reason = "silence"
    else:
        label = getattr(result, payload)
        label.label, label.probability = "x", 0.5
        label.class_probabilities["x"] = 0.5
        label.embedding.extend([0.1, 0.2])
        label.quality.snr_db, label.quality.speech_s, label.quality.reason = 4.0, 0.5, "noise"
    sent = result_to_json(result, 1, 3)

    def check(value, schema_name: str, where: str) -> None:
        documented = schemas[schema_name]["properties"]
        assert set(value) <= set(documented), (where, set(value) - set(documented))
        for key, item in value.items():
            ref = _ref(documented[key])
            if ref and isinstance(item, dict):
                check(item, ref, f"{where}.{key}")
            elif ref and isinstance(item, list):
                for element in item:
                    check(element, ref, f"{where}.{key}[]")

    check(sent, "Result", "result")


def _ref(schema: dict) -> str | None:
    """The model a property refers to (directly, in a list, or as an optional)."""
    for candidate in (schema, schema.get("items", {}), *schema.get("anyOf", [])):
        if "$ref" in candidate:
            return candidate["$ref"].rsplit("/", 1)[1]
        if "items" in candidate and "$ref" in candidate["items"]:
            return candidate["items"]["$ref"].rsplit("/", 1)[1]
    return None

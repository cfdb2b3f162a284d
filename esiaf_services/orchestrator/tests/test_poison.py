"""One poison result is refused alone; its batch neighbours are stored; counters say
what was stored. Each case is a defect found against the orchestrator over its real sockets."""
from __future__ import annotations

import pytest

from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import make_result
from esiaf_services.orchestrator.tests.helpers import wait_until

BASE_NS = 1_763_720_000_000_000_000


def stored(http, **params) -> list[dict]:
    return http.get("/results", params={"limit": 1000, **params}).json()["items"]


def poison_results(component: str) -> list[bytes]:
    huge = make_result(component, "emotion", "s", (BASE_NS, BASE_NS + 10**9), 1,
                       emotion={"label": "angry", "probability": 1.0,
                                "class_probabilities": {"angry": 1.7e308, "sad": -1.7e308}})
    nan = make_result(component, "vad", "s", (BASE_NS, BASE_NS + 10**9), 2, vad={"probability": float("nan")})
    endless = make_result(component, "vad", "s", (BASE_NS, 2**63 - 1), 3, vad={"probability": 0.5})
    backwards = make_result(component, "vad", "s", (BASE_NS, BASE_NS), 4, vad={"probability": 0.5})
    backwards.span.start_ns = BASE_NS + 10**9  # the SDK refuses to make it: a peer may still send it
    return [r.SerializeToString() for r in (huge, nan, endless, backwards)]


def test_a_poison_result_is_refused_alone_and_its_batch_is_stored(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    emotion = component("emotion", kind="emotion", inputs=["vad/speech"])
    poisons = poison_results("emotion")
    valid = 200
    for i in range(valid):  # sent back to back: they arrive in batches of up to 64 together
        asr.send_result(stream_id="s", start_ns=BASE_NS + i * 10**9, end_ns=BASE_NS + i * 10**9 + 5 * 10**8)
        if i % 10 == 0:
            emotion.push.send_multipart([b"result", poisons[(i // 10) % len(poisons)]])
            emotion.push.send_multipart([b"end_of_stream", b"[" * 100_000])
    wait_until(lambda: len(stored(http, stream="s", type="speech")) == valid, 20, "every valid result stored")
    counters = orch.core.ingest.counters
    assert counters["results"] == valid  # what was stored, not what arrived
    assert counters["refused"] == 40 and counters["refused_bad_result"] == 20
    assert counters["refused_bad_end_of_stream"] == 20
    assert counters["lost_in_db_error"] == 0
    assert stored(http, type="emotion") == []


def test_an_endless_span_does_not_corrupt_the_streams_fusions(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    ssl = component("ssl", kind="ssl", inputs=["grabber/audio"])
    ssl.emit("ssl", (BASE_NS, BASE_NS + 10**9), stream_id="s",
             ssl={"directions": [{"azimuth_deg": 90.0, "probability": 0.9}]})
    ssl.push.send_multipart([b"result", make_result("ssl", "ssl", "s", (BASE_NS, 2**63 - 1), 99,
                                                    ssl={"directions": [{"azimuth_deg": 10.0}]}).SerializeToString()])
    ssl.emit("ssl", (BASE_NS + 10**9, BASE_NS + 2 * 10**9), stream_id="s",
             ssl={"directions": [{"azimuth_deg": 90.0, "probability": 0.9}]})
    wait_until(lambda: len(stored(http, stream="s", type="ssl")) == 2, 10, "the valid ssl results")
    asr.send_result(stream_id="s", start_ns=BASE_NS, end_ns=BASE_NS + 2 * 10**9)
    ssl.end_of_stream("s")
    fused = wait_until(lambda: http.get("/fused", params={"stream": "s"}).json()["items"], 10, "the fused result")
    assert fused[0]["completion"] == "complete"
    assert round(fused[0]["aggregates"]["ssl"]["azimuth_deg"]) == 90
    assert orch.core.ingest.counters["refused_bad_result"] == 1


@pytest.mark.parametrize("size", [300_000, 5_000_000])
def test_an_oversized_result_is_refused_without_decoding_it(orch, component, http, size):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    big = pb.Result(component="asr", type=pb.RESULT_TYPE_SPEECH, stream_id="s")
    big.span.start_ns, big.span.end_ns = BASE_NS, BASE_NS + 1
    big.speech.hypotheses.add(text="x" * size, probability=0.5)
    asr.push.send_multipart([b"result", big.SerializeToString()])
    asr.send_result(stream_id="s", start_ns=BASE_NS, end_ns=BASE_NS + 10)
    wait_until(lambda: len(stored(http, stream="s")) == 1, 10, "the valid result")
    assert orch.core.ingest.counters["refused_bad_result"] == 1

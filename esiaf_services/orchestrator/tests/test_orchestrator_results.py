"""The results plane over real PUSH sockets: storage, fused results on the websocket, queries,
end of stream."""
from __future__ import annotations

import json

import httpx
import pytest
from websockets.sync.client import connect

from esiaf.proto import esiaf_pb2 as pb
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body, wait_until

START_NS = 1_763_720_000_123_000_000
END_NS = 1_763_720_001_850_000_000
ANCHOR_KEYS = {"id", "component", "instance", "type", "stream_id", "span", "produced_ns", "received_ns",
               "latency_ms", "sequence", "speech"}


def recv_json(ws, timeout_s: float = 5.0) -> dict:
    return json.loads(ws.recv(timeout=timeout_s))


def stored_count(http, **params) -> int:
    return len(http.get("/results", params={"limit": 1000, **params}).json()["items"])


def test_speech_result_is_stored_and_published_fused(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    with connect(f"{orch.ws_url}/ws/fused") as ws:
        sent = asr.send_result(start_ns=START_NS, end_ns=END_NS, text="go forward ten meters")
        fused = recv_json(ws)

    anchor = fused["anchor"]
    assert set(anchor) == ANCHOR_KEYS
    assert anchor["id"] == 1 and anchor["component"] == "asr" and anchor["type"] == "speech"
    assert anchor["stream_id"] == "default" and anchor["sequence"] == 1
    assert anchor["span"] == {"start_ns": START_NS, "end_ns": END_NS}
    assert anchor["produced_ns"] == sent.produced_ns
    assert isinstance(anchor["received_ns"], int) and anchor["received_ns"] >= sent.produced_ns
    assert anchor["latency_ms"] == pytest.approx((anchor["received_ns"] - END_NS) / 1e6, abs=1e-3)
    assert anchor["speech"] == {"hypotheses": [{
        "text": "go forward ten meters", "probability": 0.93,
        "words": [{"word": "go", "start_ns": START_NS, "end_ns": START_NS + 100_000_000,
                   "probability": 0.99}],
        "raw_text": "", "match_score": 0.0, "out_of_set": False, "logprob": 0.0, "raw_logprob": 0.0,
        "margin": 0.0}]}  # no closed set: nothing matched
    assert {k: v for k, v in fused.items() if k not in ("anchor", "published_ns")} == {
        "type": "fused_result", "id": 1, "revision": 1, "fusion": "speech",
        # the default fusion fuses ssl, emotion, gender and voice_id; none is running, so nothing waits
        "stream_id": "default", "results": {"ssl": [], "emotion": [], "gender": [], "voice_id": []},
        "aggregates": {"ssl": None, "emotion": None, "gender": None, "voice_id": None}, "completion": "complete",
        "missing_components": [], "missing": [], "seq": 1, "playback_overlap": 0.0, "source": "person", "omitted": {}}
    assert isinstance(fused["published_ns"], int)
    assert fused["published_ns"] >= anchor["received_ns"]

    assert http.get("/results").json() == {"items": [anchor], "next_after_id": 1}
    assert http.get("/fused").json() == {"items": [fused], "next_after_id": 1}
    listed = http.get("/components").json()["items"]
    assert listed[0]["results_received"] == 1


def test_queries_filter_by_stream_type_component_and_time(component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    asr.send_result(stream_id="a", start_ns=0, end_ns=10)        # fused 1
    asr.send_result(stream_id="a", start_ns=20, end_ns=30)       # fused 2
    asr.send_result(stream_id="b", start_ns=5, end_ns=15)        # fused 3
    vad.send_result(stream_id="a", start_ns=0, end_ns=30, type_=pb.RESULT_TYPE_VAD)
    wait_until(lambda: stored_count(http) == 4, what="4 stored results")

    def fused_spans(**params):
        items = http.get("/fused", params=params).json()["items"]
        return [(f["stream_id"], f["anchor"]["span"]["start_ns"]) for f in items]

    assert fused_spans() == [("a", 0), ("a", 20), ("b", 5)]
    assert fused_spans(stream="a") == [("a", 0), ("a", 20)]
    assert fused_spans(start_ns=12, end_ns=19) == [("b", 5)]      # overlap, not containment
    assert fused_spans(stream="a", start_ns=25) == [("a", 20)]
    assert fused_spans(end_ns=4) == [("a", 0)]
    assert fused_spans(fusion="speech", stream="b") == [("b", 5)]
    assert fused_spans(fusion="other") == []

    first = http.get("/fused", params={"limit": 2}).json()
    assert [f["id"] for f in first["items"]] == [1, 2] and first["next_after_id"] == 2
    rest = http.get("/fused", params={"after_id": 2}).json()
    assert [f["id"] for f in rest["items"]] == [3] and rest["next_after_id"] == 3
    assert http.get("/fused", params={"after_id": 3}).json() == {"items": [], "next_after_id": 3}

    assert stored_count(http, type="vad") == 1
    assert stored_count(http, component="asr") == 3
    assert stored_count(http, stream="a", type="speech", start_ns=11, end_ns=19) == 0
    assert stored_count(http, stream="a", start_ns=11, end_ns=19) == 1  # the vad result


def test_websocket_sends_backlog_after_id_then_live_without_duplicates(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    for start in (0, 10, 20):
        asr.send_result(stream_id="s", start_ns=start, end_ns=start + 5)
    wait_until(lambda: len(http.get("/fused").json()["items"]) == 3, what="3 fused results")
    with connect(f"{orch.ws_url}/ws/fused?after_id=1&stream=s") as ws:
        assert [recv_json(ws)["id"] for _ in range(2)] == [2, 3]
        asr.send_result(stream_id="other", start_ns=30, end_ns=35)  # filtered out
        asr.send_result(stream_id="s", start_ns=40, end_ns=45)
        assert recv_json(ws)["id"] == 5


def test_bad_messages_are_counted_and_ingest_goes_on(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    asr.push.send_multipart([b"result", b"\xff\xff not a protobuf"])
    asr.push.send_multipart([b"result", pb.Result(component="asr").SerializeToString()])
    asr.push.send_multipart([b"weird", b"{}"])
    asr.push.send_multipart([b"end_of_stream", b"not json"])
    asr.send_result()
    wait_until(lambda: stored_count(http) == 1, what="the good result")
    counters = orch.core.ingest.counters
    assert counters["bad_results"] == 2 and counters["bad_messages"] == 2


def test_stream_end_after_every_input_component_said_so(orch, component, http):
    component("grabber", outputs=["audio/raw"])  # no inputs: not waited for
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    with connect(f"{orch.ws_url}/ws/fused?stream=s1") as ws:
        vad.end_of_stream("s1")
        vad.send_result(stream_id="marker", type_=pb.RESULT_TYPE_VAD)  # same socket, after eos
        wait_until(lambda: stored_count(http, stream="marker") == 1, what="vad's eos handled")
        asr.send_result(stream_id="s1", start_ns=0, end_ns=10)
        asr.end_of_stream("s1")
        # Had vad's end alone ended the stream, stream_end would come before the fused result.
        assert recv_json(ws)["type"] == "fused_result"
        assert recv_json(ws) == {"type": "stream_end", "stream_id": "s1"}

        # A new result after the end starts the stream again; it ends when all say so again.
        asr.send_result(stream_id="s1", start_ns=20, end_ns=30)
        assert recv_json(ws)["anchor"]["span"]["start_ns"] == 20
        asr.end_of_stream("s1")
        asr.send_result(stream_id="s1", start_ns=40, end_ns=50)  # straggler: asr already ended
        assert recv_json(ws)["anchor"]["span"]["start_ns"] == 40
        vad.end_of_stream("s1")
        assert recv_json(ws) == {"type": "stream_end", "stream_id": "s1"}


def test_stream_end_stops_waiting_for_a_component_that_left(orch, component, http):
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    emotion = component("emotion", kind="emotion", inputs=["vad/speech"])
    with connect(f"{orch.ws_url}/ws/fused") as ws:
        vad.end_of_stream("s2")
        vad.send_result(stream_id="marker", type_=pb.RESULT_TYPE_VAD)
        wait_until(lambda: stored_count(http, stream="marker") == 1, what="vad's eos handled")
        assert http.delete(f"/components/{emotion.id}").status_code == 204
        assert recv_json(ws) == {"type": "stream_end", "stream_id": "s2"}


def test_a_replayed_stream_does_not_teach_latencies(orch, component, http):
    """A stream announced as faster than real time (the grabber's --fast: "realtime": false): its
    capture times run ahead of the clock, so its results must not set the timeouts of a later
    real-time stream."""
    import time
    now = time.time_ns()
    assert http.put("/streams/replay", json={"start_ns": now, "source": "grabber",
                                            "info": {"realtime": False}}).status_code == 200
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    asr.send_result(stream_id="replay", start_ns=now - 51 * 10**9, end_ns=now - 50 * 10**9)  # "50 s" late
    asr.send_result(stream_id="live", start_ns=now - 2 * 10**9, end_ns=now - 10**9)
    wait_until(lambda: stored_count(http) == 2, what="both results")
    [latency] = http.get("/latency", params={"component": "asr"}).json()["items"]
    assert latency["count"] == 1 and 1000 <= latency["mean_ms"] < 10_000, latency  # the live stream's only


@pytest.mark.parametrize("comes_back", [True, "ends-under-its-old-id", False],
                         ids=["comes-back", "ends-under-its-old-id", "never-comes-back"])
def test_a_component_that_stalls_holds_the_stream_end_for_its_grace(make_orchestrator, zctx, comes_back):
    """An analyser silent past dead_after_s (busy in C code on a loaded machine, frozen) has not ended
    the stream: its end waits stream_end_stall_grace_s for it to come back and finish."""
    import time

    from esiaf_services.orchestrator.tests.helpers import Heartbeater
    orch = make_orchestrator(dead_after_s=0.6, stream_end_stall_grace_s=2.0)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http, connect(f"{orch.ws_url}/ws/fused?stream=s3") as ws:
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"],
                                                       outputs=["vad/speech"]))
        asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
        beating = Heartbeater([vad])  # the asr stays silent: it is declared dead
        try:
            wait_until(lambda: asr.id not in {c["component_id"] for c in http.get("/components").json()["items"]},
                       what="the asr dead")
            dead_at = time.monotonic()
            vad.end_of_stream("s3")
            if comes_back == "ends-under-its-old-id":
                # its heartbeat thread registers again (a new id) while its end_of_stream, sent by the
                # decoding thread, still carries the old one
                asr.send_result(stream_id="s3", start_ns=0, end_ns=10)
                assert recv_json(ws)["type"] == "fused_result"
                stalled, asr = asr, FakeComponent(zctx, http, component_body("asr", kind="speech",
                                                                             inputs=["vad/speech"]))
                stalled.end_of_stream("s3")
                assert recv_json(ws) == {"type": "stream_end", "stream_id": "s3"}  # not waiting for the new id
                stalled.close()
                assert time.monotonic() - dead_at < 2.0
            elif comes_back:  # registers again (a new instance), sends its backlog, ends the stream
                asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
                asr.send_result(stream_id="s3", start_ns=0, end_ns=10)
                asr.end_of_stream("s3")
                assert recv_json(ws)["type"] == "fused_result"  # not lost after a premature stream end
                assert recv_json(ws) == {"type": "stream_end", "stream_id": "s3"}
                assert time.monotonic() - dead_at < 2.0
            else:
                assert recv_json(ws, timeout_s=5.0) == {"type": "stream_end", "stream_id": "s3"}
                assert time.monotonic() - dead_at >= 2.0 - 0.5  # held for the grace (less the time to see it dead)
        finally:
            beating.stop()
            vad.close()
            asr.close()


def test_results_survive_a_restart_and_ids_go_on(make_orchestrator, zctx, tmp_path):
    db = str(tmp_path / "kept.db")
    for run, expected_ids in ((1, [1]), (2, [1, 2])):
        orch = make_orchestrator(db_path=db)
        with httpx.Client(base_url=orch.url, timeout=5.0) as http:
            asr = FakeComponent(zctx, http, component_body("asr", kind="speech",
                                                           inputs=["vad/speech"]))
            asr.send_result(start_ns=run, end_ns=run + 1)
            wait_until(lambda run=run: stored_count(http) == run, what=f"run {run}'s result")
            assert [r["id"] for r in http.get("/results").json()["items"]] == expected_ids
            assert [f["id"] for f in http.get("/fused").json()["items"]] == expected_ids
            asr.close()
        orch.stop()


def test_an_utterance_in_flight_on_a_recogniser_that_dies_is_fused_with_it_missing(make_orchestrator, zctx):
    """An asr instance killed with an utterance it had taken but not answered: the VAD's
    segment is fused without it (anchored on the segment, the asr missing), never silently lost;
    what the asr answered before and another stream it did not serve are left alone."""
    from esiaf_services.orchestrator.tests.helpers import Heartbeater
    orch = make_orchestrator(dead_after_s=0.6)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http, connect(f"{orch.ws_url}/ws/fused?stream=s4") as ws:
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"],
                                                       outputs=["vad/speech"]))
        asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
        beating = Heartbeater([vad, asr])
        try:
            vad.send_result(stream_id="s4", start_ns=START_NS, end_ns=END_NS, type_=pb.RESULT_TYPE_VAD)
            asr.send_result(stream_id="s4", start_ns=START_NS, end_ns=END_NS, text="bring me a coke")
            answered = recv_json(ws)
            assert answered["anchor"]["type"] == "speech" and answered["completion"] == "complete"
            in_flight = (END_NS + 1_000_000_000, END_NS + 2_500_000_000)
            vad.send_result(stream_id="s4", start_ns=in_flight[0], end_ns=in_flight[1], type_=pb.RESULT_TYPE_VAD)
            wait_until(lambda: stored_count(http, type="vad") == 2, what="the second segment stored")
            beating.drop(asr)  # killed: silent from now on
            orphan = recv_json(ws, timeout_s=5.0)  # once it is declared dead (0.6 s)
            assert orphan["type"] == "fused_result" and orphan["completion"] == "components_gone"
            assert orphan["anchor"]["type"] == "vad"
            assert orphan["anchor"]["span"] == {"start_ns": in_flight[0], "end_ns": in_flight[1]}
            assert orphan["missing"] == [{"component": "asr", "type": "speech", "reason": "gone"}]
            with pytest.raises(TimeoutError):
                recv_json(ws, timeout_s=1.0)  # the answered utterance is not fused again
        finally:
            beating.stop()
            vad.close()
            asr.close()


def test_an_utterance_a_live_recogniser_passed_by_is_fused_with_it_missing(make_orchestrator, zctx):
    """Past saturation a recogniser loses an utterance's audio and answers the next one.
    The passed-by segment is fused without it (reason ``skipped``) when the later answer comes, and
    one after its last answer when it ends the stream: reported, not silently lost."""
    orch = make_orchestrator()
    second = 2_000_000_000
    spans = [(START_NS + i * 3 * second, START_NS + i * 3 * second + second) for i in range(4)]
    with httpx.Client(base_url=orch.url, timeout=5.0) as http, connect(f"{orch.ws_url}/ws/fused?stream=s5") as ws:
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"],
                                                       outputs=["vad/speech"]))
        asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
        try:
            for start, end in spans:
                vad.send_result(stream_id="s5", start_ns=start, end_ns=end, type_=pb.RESULT_TYPE_VAD)
            wait_until(lambda: stored_count(http, type="vad") == 4, what="the segments stored")
            asr.send_result(stream_id="s5", start_ns=spans[0][0], end_ns=spans[0][1], text="bring me a coke")
            assert recv_json(ws)["anchor"]["type"] == "speech"
            asr.send_result(stream_id="s5", start_ns=spans[2][0], end_ns=spans[2][1], text="go to the kitchen")
            skipped, answered = recv_json(ws), recv_json(ws)
            assert skipped["anchor"]["type"] == "vad" and skipped["completion"] == "timed_out"
            assert skipped["anchor"]["span"] == {"start_ns": spans[1][0], "end_ns": spans[1][1]}
            assert skipped["missing"] == [{"component": "asr", "type": "speech", "reason": "skipped"}]
            assert answered["anchor"]["type"] == "speech"
            asr.end_of_stream("s5")
            last = recv_json(ws)
            assert last["anchor"]["span"] == {"start_ns": spans[3][0], "end_ns": spans[3][1]}
            assert last["missing"][0]["reason"] == "skipped"
            with pytest.raises(TimeoutError):
                recv_json(ws, timeout_s=1.0)  # each once
        finally:
            vad.close()
            asr.close()

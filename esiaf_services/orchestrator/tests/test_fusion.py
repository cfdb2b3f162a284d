"""Fusion situations, one test each: scripted fake components (real DEALER and PUSH sockets)
against the real orchestrator process, its real SQLite file, a real websocket client.

Capture times are recent wall-clock times, as a grabber stamps them, so that latencies and
deadlines (window end + timeout) mean what they mean in a running pipeline.
"""
from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator

import pytest
from websockets.sync.client import connect

from esiaf.results import ssl_direction
from esiaf.tools.testing import Orchestrator
from esiaf_services.orchestrator.tests.helpers import FakeComponent, Heartbeater, component_body, wait_until

S = 1_000_000_000  # one second in ns
UTTERANCE = {"name": "utterance", "anchor": "speech", "fuse": ["ssl", "emotion"]}
# A long initial timeout: a fusion that should complete never passes by timing out instead.
BASE_CONFIG = {"heartbeat_interval_s": 1.0, "dead_after_s": 30.0, "fusions": [UTTERANCE],
               "timeouts": {"initial_s": 10.0}}


@pytest.fixture
def start(tmp_path) -> Iterator:
    """Starts the orchestrator process with settings on top of BASE_CONFIG."""
    started: list[Orchestrator] = []

    def make(**config) -> Orchestrator:
        orchestrator = Orchestrator(tmp_path, {**BASE_CONFIG, **config})
        started.append(orchestrator)
        return orchestrator

    yield make
    for orchestrator in started:
        orchestrator.close()


@pytest.fixture
def fake(zctx) -> Iterator:
    made: list[FakeComponent] = []

    def make(orchestrator: Orchestrator, name: str, kind: str) -> FakeComponent:
        component = FakeComponent(zctx, orchestrator.http,
                                  component_body(name, kind=kind, inputs=["in"]))
        made.append(component)
        return component

    yield make
    for component in made:
        component.close()


def recv(ws, timeout_s: float = 5.0) -> dict:
    return json.loads(ws.recv(timeout=timeout_s))


def nothing_more(ws, timeout_s: float = 0.3) -> bool:
    try:
        ws.recv(timeout=timeout_s)
    except TimeoutError:
        return True
    return False


def spans(fused: dict, type_name: str) -> list[tuple[int, int]]:
    return [(r["span"]["start_ns"], r["span"]["end_ns"]) for r in fused["results"][type_name]]


def stored(orchestrator: Orchestrator, count: int) -> None:
    wait_until(lambda: len(orchestrator.http.get("/results", params={"limit": 1000})
                           .json()["items"]) >= count, what=f"{count} stored results")


def emotion(label: str = "happy", p: float = 0.7, other: str = "neutral") -> dict:
    return {"emotion": {"label": label, "probability": p,
                        "class_probabilities": {label: p, other: round(1 - p, 6)}}}


def ssl_at(azimuth_deg: float) -> dict:
    return {"ssl": {"directions": [ssl_direction(azimuth_deg)]}}


def utterance_components(orchestrator, fake):
    return (fake(orchestrator, "asr", "speech"), fake(orchestrator, "ssl", "ssl"),
            fake(orchestrator, "emotion", "emotion"))


def test_results_before_and_after_the_anchor(start, fake):
    orchestrator = start()
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t1 = time.time_ns()
    t0 = t1 - 2 * S
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        ssl.emit("ssl", (t0 - S, t0), **ssl_at(180))  # only touches the window: not in it
        ssl.emit("ssl", (t0, t0 + S), **ssl_at(350))  # before the anchor
        asr.emit("speech", (t0, t1), speech={"hypotheses": [{"text": "hello", "probability": 0.9}]})
        ssl.emit("ssl", (t0 + S, t1), **ssl_at(10))  # after it
        emo.emit("emotion", (t0 - S, t1), **emotion())  # after it, starting before the window
        fused = recv(ws)
        assert nothing_more(ws)
    assert fused["completion"] == "complete" and fused["missing"] == []
    assert fused["anchor"]["speech"]["hypotheses"][0]["text"] == "hello"
    assert spans(fused, "ssl") == [(t0, t0 + S), (t0 + S, t1)]
    assert spans(fused, "emotion") == [(t0 - S, t1)]
    ssl_aggregate = fused["aggregates"]["ssl"]  # 350° and 10°: 0°, never 180°
    assert min(ssl_aggregate["azimuth_deg"], 360 - ssl_aggregate["azimuth_deg"]) < 1e-6
    assert ssl_aggregate["overlap_s"] == pytest.approx(2.0)
    assert fused["aggregates"]["emotion"]["label"] == "happy"
    assert fused["aggregates"]["emotion"]["distribution"] == {"happy": 0.7, "neutral": 0.3}
    assert orchestrator.http.get("/fused").json()["items"] == [fused]


def test_out_of_order_results_complete_only_when_coverage_is_contiguous(start, fake):
    # min_s: the ssl's latency is learned from these results (2 s for the late one), and a timeout of
    # 1.5 x that passed before the gap was filled on a loaded machine (the fusion then timed out)
    orchestrator = start(timeouts={"initial_s": 10.0, "min_s": 10.0})
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t1 = time.time_ns()
    t0 = t1 - 3 * S
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        ssl.emit("ssl", (t0 + 2 * S, t1), **ssl_at(90))  # reaches the end, but leaves a gap
        emo.emit("emotion", (t0, t1), nothing="silence")  # covered, no result
        asr.emit("speech", (t0, t1), speech={"hypotheses": []})
        ssl.emit("ssl", (t0, t0 + S), **ssl_at(80))
        stored(orchestrator, 4)
        assert orchestrator.http.get("/fused").json()["items"] == []
        assert orchestrator.http.get("/fusions/stats").json()["open_fusions"] == 1
        ssl.emit("ssl", (t0 + S, t0 + 2 * S), nothing="no source")  # fills the gap
        fused = recv(ws)
    assert fused["completion"] == "complete"
    assert spans(fused, "ssl") == [(t0, t0 + S), (t0 + 2 * S, t1)]  # `nothing` is coverage only
    assert fused["results"]["emotion"] == [] and fused["aggregates"]["emotion"] is None
    assert 80 < fused["aggregates"]["ssl"]["azimuth_deg"] < 90


def test_results_strictly_inside_the_window_are_included_before_and_after_the_anchor(start, fake):
    orchestrator = start()
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t1 = time.time_ns()
    t0 = t1 - 2 * S
    inside_before, inside_after = (t0 + S // 4, t0 + S // 2), (t0 + S // 2, t0 + 3 * S // 2)
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        ssl.emit("ssl", (t0, inside_before[0]), nothing="no source")
        ssl.emit("ssl", inside_before, **ssl_at(45))
        emo.emit("emotion", (t0, inside_before[0]), nothing="silence")
        emo.emit("emotion", inside_before, **emotion("sad"))
        asr.emit("speech", (t0, t1), speech={"hypotheses": []})
        ssl.emit("ssl", inside_after, **ssl_at(45))  # live, strictly inside: the original lost it
        emo.emit("emotion", inside_after, **emotion("sad"))
        ssl.emit("ssl", (inside_after[1], t1), nothing="no source")
        emo.emit("emotion", (inside_after[1], t1 + S), nothing="silence")
        fused = recv(ws)
    assert fused["completion"] == "complete"
    assert spans(fused, "ssl") == [inside_before, inside_after]
    assert spans(fused, "emotion") == [inside_before, inside_after]
    assert fused["aggregates"]["emotion"]["label"] == "sad"


def test_consecutive_overlapping_anchors_each_get_their_own_window(start, fake):
    orchestrator = start()
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t0 = time.time_ns() - 4 * S
    first, second = (t0, t0 + 2 * S), (t0 + 3 * S // 2, t0 + 7 * S // 2)
    half = S // 2
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        asr.emit("speech", first, speech={"hypotheses": []})
        asr.emit("speech", second, speech={"hypotheses": []})
        for i in range(7):  # 0.5 s chunks from t0 to t0 + 3.5 s
            ssl.emit("ssl", (t0 + i * half, t0 + (i + 1) * half), **ssl_at(10 * i))
        emo.emit("emotion", first, **emotion("happy"))
        emo.emit("emotion", (first[1], second[1]), **emotion("angry"))
        fused = [recv(ws), recv(ws)]
    by_start = {f["anchor"]["span"]["start_ns"]: f for f in fused}
    a, b = by_start[first[0]], by_start[second[0]]
    assert a["id"] != b["id"]
    assert spans(a, "ssl") == [(t0 + i * half, t0 + (i + 1) * half) for i in range(4)]
    assert spans(b, "ssl") == [(t0 + i * half, t0 + (i + 1) * half) for i in range(3, 7)]
    assert spans(a, "emotion") == [first]  # the next one only touches its end
    assert spans(b, "emotion") == [first, (first[1], second[1])]
    assert a["aggregates"]["emotion"]["label"] == "happy"
    assert b["aggregates"]["emotion"]["label"] == "angry"  # 1.5 s angry against 0.5 s happy
    assert b["aggregates"]["emotion"]["distribution"]["angry"] == pytest.approx(1.5 * 0.7 / 2.0)


def send_with_latency(component: FakeComponent, latency_ns: int, count: int, type_name: str,
                      **payload) -> int:
    """Results whose audio ended ``latency_ns`` before they are sent; returns the last end."""
    end = 0
    for _ in range(count):
        end = time.time_ns() - latency_ns
        component.emit(type_name, (end - S // 2, end), **payload)
    return end


def test_a_component_that_never_answers_times_out_at_factor_times_its_mean_latency(start, fake):
    orchestrator = start()
    asr, ssl, emo = utterance_components(orchestrator, fake)
    emotion_end = send_with_latency(emo, 400_000_000, 3, "emotion", **emotion())
    stored(orchestrator, 3)
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        t1 = time.time_ns()
        t0 = emotion_end  # emotion covered audio up to here, then falls silent
        ssl.emit("ssl", (t0, t1), **ssl_at(0))
        asr.emit("speech", (t0, t1), speech={"hypotheses": []})
        fused = recv(ws, timeout_s=5.0)
    [emotion_latency] = orchestrator.http.get("/latency", params={"component": "emotion"}).json()["items"]
    assert emotion_latency["count"] == 3
    assert 400 <= emotion_latency["mean_ms"] < 700  # 400 ms + transit on a loaded machine
    assert emotion_latency["timeout_ms"] == pytest.approx(1.5 * emotion_latency["mean_ms"], abs=0.01)
    waited_ms = (fused["published_ns"] - t1) / 1e6
    assert emotion_latency["timeout_ms"] - 5 <= waited_ms <= emotion_latency["timeout_ms"] + 300
    assert fused["completion"] == "timed_out"
    assert fused["missing"] == [{"component": "emotion", "type": "emotion", "reason": "timed_out"}]
    assert fused["missing_components"] == ["emotion"] and spans(fused, "ssl") == [(t0, t1)]


def test_a_component_dying_mid_fusion_is_not_waited_for(start, fake):
    orchestrator = start(heartbeat_interval_s=0.25, dead_after_s=1.0)
    asr, ssl, emo = utterance_components(orchestrator, fake)
    beating = Heartbeater([asr, ssl])
    try:
        t1 = time.time_ns()
        t0 = t1 - S
        with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
            emo.emit("emotion", (t0 - S, t0), **emotion())  # alive, then silent: dies
            ssl.emit("ssl", (t0, t1), **ssl_at(30))
            asr.emit("speech", (t0, t1), speech={"hypotheses": []})
            fused = recv(ws, timeout_s=5.0)
    finally:
        beating.stop()
    assert fused["completion"] == "components_gone"
    assert fused["missing"] == [{"component": "emotion", "type": "emotion", "reason": "gone"}]
    assert (fused["published_ns"] - t1) / 1e9 < 3.0  # its death, not the 10 s timeout
    dead = orchestrator.http.get("/components", params={"include_dead": True}).json()["items"]
    assert [c["status"] for c in dead if c["name"] == "emotion"] == ["dead"]


def test_a_late_result_publishes_revision_2_on_the_websocket(start, fake):
    orchestrator = start(timeouts={"initial_s": 0.3})
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t1 = time.time_ns()
    t0 = t1 - S
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        emo.emit("emotion", (t0, t1), **emotion())
        asr.emit("speech", (t0, t1), speech={"hypotheses": []})
        first = recv(ws)
        assert first["revision"] == 1 and first["completion"] == "timed_out"
        assert first["missing_components"] == ["ssl"] and first["results"]["ssl"] == []
        ssl.emit("ssl", (t0, t1), **ssl_at(270))  # too late for revision 1
        second = recv(ws)
    assert second["id"] == first["id"] and second["revision"] == 2
    assert spans(second, "ssl") == [(t0, t1)] and second["aggregates"]["ssl"]["azimuth_deg"] == 270
    assert second["missing"] == [] and second["completion"] == "timed_out"  # how rev 1 was decided
    assert spans(second, "emotion") == spans(first, "emotion")
    assert orchestrator.http.get("/fused").json()["items"] == [second]
    assert second["seq"] > first["seq"]
    # a consumer that had revision 1 resumes without missing revision 2 (after_id cannot:
    # the id did not change)
    with connect(f"{orchestrator.ws_url}/ws/fused?after_seq={first['seq']}") as ws:
        assert recv(ws) == second and nothing_more(ws)


def test_restart_on_the_same_database_keeps_timeouts_warm_and_loses_nothing(start, zctx):
    orchestrator = start()

    def components() -> tuple[FakeComponent, ...]:
        return tuple(FakeComponent(zctx, orchestrator.http, component_body(n, kind=d, inputs=["in"]))
                     for n, d in (("asr", "speech"), ("ssl", "ssl"), ("emotion", "emotion")))

    asr, ssl, emo = components()
    emotion_end = send_with_latency(emo, S, 3, "emotion", **emotion())
    stored(orchestrator, 3)  # its latency is known before the anchor comes
    t1 = time.time_ns()
    ssl.emit("ssl", (emotion_end, t1), **ssl_at(120))
    asr.emit("speech", (emotion_end, t1), speech={"hypotheses": [{"text": "before", "probability": 1}]})
    wait_until(lambda: orchestrator.http.get("/fusions/stats").json()["open_fusions"] == 1,
               what="the fusion waiting for emotion")
    latency_before = orchestrator.http.get("/latency").json()["items"]
    orchestrator.kill()  # SIGKILL, while the fusion waits (deadline: 1.5 s after t1)
    for component in (asr, ssl, emo):
        component.close()

    orchestrator.start()
    assert orchestrator.http.get("/latency").json()["items"] == latency_before
    with connect(f"{orchestrator.ws_url}/ws/fused?after_id=0") as ws:
        restored = recv(ws)  # published after the restart, at its original deadline
        assert restored["anchor"]["speech"]["hypotheses"][0]["text"] == "before"
        assert restored["completion"] == "timed_out" and spans(restored, "ssl") == [(emotion_end, t1)]
        asr, ssl, emo = components()
        try:
            t3 = time.time_ns()
            t2 = t3 - S
            ssl.emit("ssl", (t2, t3), **ssl_at(120))
            asr.emit("speech", (t2, t3), speech={"hypotheses": []})
            after = recv(ws)
        finally:
            for component in (asr, ssl, emo):
                component.close()
    [emotion_latency] = [c for c in latency_before if c["component"] == "emotion"]
    waited_ms = (after["published_ns"] - t3) / 1e6  # the warm timeout, not the initial 10 s
    assert emotion_latency["timeout_ms"] - 5 <= waited_ms <= emotion_latency["timeout_ms"] + 500
    assert after["id"] == restored["id"] + 1
    results = orchestrator.http.get("/results").json()["items"]
    assert len(results) == 7 and [r["id"] for r in results] == list(range(1, 8))


def test_two_fusions_with_different_anchors_run_at_once(start, fake):
    voice = {"name": "voice", "anchor": "vad", "fuse": ["ssl", "gender"]}
    orchestrator = start(fusions=[UTTERANCE, voice])
    asr, ssl, emo = utterance_components(orchestrator, fake)
    vad, gender = fake(orchestrator, "vad", "vad"), fake(orchestrator, "gender", "gender")
    t1 = time.time_ns()
    t0 = t1 - 2 * S
    with connect(f"{orchestrator.ws_url}/ws/fused?fusion=utterance") as by_speech, \
            connect(f"{orchestrator.ws_url}/ws/fused?fusion=voice") as by_voice:
        vad.emit("vad", (t0, t1), vad={"probability": 0.9})
        asr.emit("speech", (t0 + S // 4, t1 - S // 4), speech={"hypotheses": []})
        ssl.emit("ssl", (t0, t1), **ssl_at(200))
        emo.emit("emotion", (t0, t1), **emotion())
        gender.emit("gender", (t0, t1), gender={"label": "female", "probability": 0.8})
        speech_fused, voice_fused = recv(by_speech), recv(by_voice)
        assert nothing_more(by_speech) and nothing_more(by_voice, 0.05)
    assert speech_fused["fusion"] == "utterance" and voice_fused["fusion"] == "voice"
    assert set(speech_fused["results"]) == {"ssl", "emotion"}
    assert set(voice_fused["results"]) == {"ssl", "gender"}
    assert speech_fused["completion"] == voice_fused["completion"] == "complete"
    assert voice_fused["aggregates"]["gender"]["label"] == "female"
    assert speech_fused["anchor"]["type"] == "speech" and voice_fused["anchor"]["type"] == "vad"


def test_a_flood_of_results_in_one_window_is_listed_bounded_and_counted(start, fake):
    """An analyser that sends 1,000 results for one utterance: the fused result lists 200 of them,
    evenly over the window, counts the 800 it left out, and its aggregate still weighs all 1,000."""
    orchestrator = start()
    asr, ssl, emo = utterance_components(orchestrator, fake)
    t1 = time.time_ns()
    t0 = t1 - 2 * S
    step = 2 * S // 1000
    with connect(f"{orchestrator.ws_url}/ws/fused") as ws:
        for i in range(1000):
            ssl.emit("ssl", (t0 + i * step, t0 + (i + 1) * step), **ssl_at(90 if i < 600 else 270))
        emo.emit("emotion", (t0, t1), **emotion())
        asr.emit("speech", (t0, t1), speech={"hypotheses": [{"text": "hello", "probability": 0.9}]})
        fused = recv(ws, timeout_s=10)
    listed = fused["results"]["ssl"]
    assert len(listed) == 200 and fused["omitted"] == {"ssl": 800}
    assert listed[0]["span"]["start_ns"] == t0 and listed[-1]["span"]["end_ns"] == t1  # the first and the last
    starts = [r["span"]["start_ns"] for r in listed]
    assert starts == sorted(starts) and max(b - a for a, b in itertools.pairwise(starts)) <= 6 * step  # evenly
    assert fused["aggregates"]["ssl"]["directions"] == 1000  # the aggregate weighs every one
    assert fused["aggregates"]["ssl"]["azimuth_deg"] == pytest.approx(90, abs=1e-6)
    assert fused["results"]["emotion"] and "emotion" not in fused["omitted"]
    assert len(json.dumps(fused)) < 200_000

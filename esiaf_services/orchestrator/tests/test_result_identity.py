"""Results and end_of_stream notices are bound to their component's registration: a peer
that holds the token (or an allowed key) and knows a component id but not its registration's
control key cannot send results or a stream end in its name; they are refused, counted by reason
and never count as its life, and the real component's results beside them are all stored. A
registration again makes the old key's messages refused; a registration made before a restart of
the orchestrator is still recognised (the key is derived from a secret kept in the database)."""
from __future__ import annotations

import json
import logging
import re
import time
from types import SimpleNamespace

import httpx
import zmq
from websockets.sync.client import connect

from esiaf.binding import signed
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import make_result
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body, wait_until
from esiaf_services.orchestrator.tests.test_metrics import samples, value

BASE_NS = 1_763_720_000_000_000_000
WRONG = SimpleNamespace(key_id="k" * 16, control_key="A" * 43)  # looks like a real one


def speech(name: str, instance: str, stream_id: str, i: int, text: str) -> bytes:
    result = make_result(name, "speech", stream_id, (BASE_NS + i * 10**9, BASE_NS + i * 10**9 + 5 * 10**8), i,
                         speech={"hypotheses": [{"text": text, "probability": 1.0}]})
    result.instance = instance
    return result.SerializeToString()


def eos(component: FakeComponent, stream_id: str) -> bytes:
    return json.dumps({"component_id": component.id, "component": component.name, "stream_id": stream_id}).encode()


def stored_texts(http: httpx.Client, stream_id: str) -> list[str]:
    items = http.get("/results", params={"limit": 1000, "stream": stream_id}).json()["items"]
    return [r["speech"]["hypotheses"][0]["text"] for r in items if "speech" in r]


def pusher(zctx: zmq.Context, endpoint: str) -> zmq.Socket:
    sock = zctx.socket(zmq.PUSH)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    return sock


def test_forged_results_are_refused_counted_and_the_real_ones_beside_them_stored(orch, component, http, zctx):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    mallory = component("mallory", kind="speech", inputs=["vad/speech"])  # holds a key: its own
    stranger = pusher(zctx, asr.registration["results_endpoint"])
    valid = 150
    for i in range(valid):  # back to back: the forged ones share batches with the real ones
        asr.send(b"result", speech("asr", asr.id, "s", i, f"real {i}"))
        if i % 3 == 0:
            forged = speech("asr", asr.id, "s", i, "open the front door and disable the alarm")
            stranger.send_multipart([b"result", forged])  # no key
            stranger.send_multipart(signed(b"result", forged, WRONG))  # a made-up key
            mallory.send(b"result", forged)  # another registration's key
            altered = signed(b"result", speech("asr", asr.id, "s", i, f"real {i}"), asr.keys)
            altered[1] = forged  # the real MAC on another body
            stranger.send_multipart(altered)
    wait_until(lambda: len(stored_texts(http, "s")) == valid, 20, "every real result stored")
    time.sleep(0.3)  # anything forged that was still on its way
    assert stored_texts(http, "s") == [f"real {i}" for i in range(valid)]
    counters = orch.core.ingest.counters
    assert counters["results"] == valid
    assert counters["refused_no_key"] == 50 and counters["refused_wrong_key"] == 150
    assert orch.core.registry.get(asr.id).results_received == valid  # forged ones are not its life
    assert http.get("/fusions/stats").json()["counters"]["refused_no_key"] == 50
    metrics = samples(http)
    assert value(metrics, "esiaf_refused_messages_total", reason="wrong_key") == 150


def test_forged_results_do_not_keep_a_silent_component_alive(make_orchestrator, zctx):
    orch = make_orchestrator(heartbeat_interval_s=0.2, dead_after_s=1.0)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http:
        asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
        asr.heartbeat()
        stranger = pusher(zctx, asr.registration["results_endpoint"])
        deadline = time.monotonic() + 3.0
        i = 0
        while time.monotonic() < deadline:  # asr is silent; a stranger sends results in its name
            i += 1
            stranger.send_multipart([b"result", speech("asr", asr.id, "s", i, "forged")])
            time.sleep(0.1)
        listed = http.get("/components", params={"include_dead": True}).json()["items"]
        assert [c["status"] for c in listed if c["component_id"] == asr.id] == ["dead"]
        assert stored_texts(http, "s") == []
        asr.close()


def test_a_forged_end_of_stream_does_not_end_the_stream(orch, component, http, zctx):
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    stranger = pusher(zctx, asr.registration["results_endpoint"])
    with connect(f"{orch.ws_url}/ws/fused?stream=s1") as ws:
        for victim in (vad, asr):
            stranger.send_multipart([b"end_of_stream", eos(victim, "s1")])
            stranger.send_multipart(signed(b"end_of_stream", eos(victim, "s1"), WRONG))
        vad.end_of_stream("s1")  # the real vad: the stream still waits for the real asr
        asr.send_result(stream_id="s1", start_ns=BASE_NS, end_ns=BASE_NS + 10)
        first = json.loads(ws.recv(timeout=5))
        assert first["type"] == "fused_result", first  # no stream_end came before it
        counters = orch.core.ingest.counters
        assert counters["refused_no_key"] == 2 and counters["refused_wrong_key"] == 2
        asr.end_of_stream("s1")
        assert json.loads(ws.recv(timeout=5)) == {"type": "stream_end", "stream_id": "s1"}


def test_what_was_signed_before_a_registration_again_is_kept(orch, http, zctx):
    """A long decode starved the asr's heartbeat: declared dead, it registered again (a new key) while
    its result and stream end, signed with the old one, were on their way. They are its own: kept."""
    body = component_body("asr", kind="speech", inputs=["vad/speech"], instance="asr-a", incarnation="p1")
    asr = FakeComponent(zctx, http, body)
    old = asr.keys
    asr.registration = http.post("/components", json=body).json()  # the same process registers again
    assert asr.keys.key_id != old.key_id and asr.keys.control_key != old.control_key
    asr.push.send_multipart(signed(b"result", speech("asr", "asr-a", "s", 1, "old key"), old))
    asr.push.send_multipart(signed(b"end_of_stream", eos(asr, "s"), old))
    asr.send(b"result", speech("asr", "asr-a", "s", 2, "new key"))
    wait_until(lambda: len(stored_texts(http, "s")) == 2, what="both results")
    assert stored_texts(http, "s") == ["old key", "new key"]
    assert orch.core.ingest.counters["refused_old_key"] == 0


def test_a_registration_made_before_a_restart_is_still_recognised(make_orchestrator, tmp_path, zctx):
    db = str(tmp_path / "kept.db")
    first = make_orchestrator(db_path=db)
    with httpx.Client(base_url=first.url, timeout=5.0) as http:
        asr = FakeComponent(zctx, http, component_body("asr", kind="speech", inputs=["vad/speech"]))
    first.stop()
    second = make_orchestrator(db_path=db)  # knows no component: results queued meanwhile arrive
    with httpx.Client(base_url=second.url, timeout=5.0) as http:
        push = pusher(zctx, second.core.results_endpoint)
        push.send_multipart(signed(b"result", speech("asr", asr.id, "s", 1, "queued while away"), asr.keys))
        push.send_multipart(signed(b"result", speech("asr", asr.id, "s", 2, "forged"), WRONG))
        push.send_multipart(signed(b"result", speech("asr", "asr-unknown", "s", 3, "forged"), asr.keys))
        wait_until(lambda: stored_texts(http, "s"), what="the queued result")
        time.sleep(0.2)
        assert stored_texts(http, "s") == ["queued while away"]
        assert second.core.ingest.counters["refused_wrong_key"] == 2
    asr.close()


def test_messages_without_a_key_are_refused_before_anything_is_stored(orch, component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    asr.push.send_multipart([b"result", speech("asr", asr.id, "s", 1, "no key")])  # no key: not bound
    asr.push.send_multipart([b"result", speech("asr", asr.id, "s", 2, "bad"), b"", b"x"])
    asr.send_result(stream_id="s", start_ns=BASE_NS + 5 * 10**9, end_ns=BASE_NS + 6 * 10**9, text="signed")
    wait_until(lambda: stored_texts(http, "s"), what="the signed result")
    time.sleep(0.2)
    assert stored_texts(http, "s") == ["signed"]
    counters = orch.core.ingest.counters
    assert counters["refused_no_key"] == 1 and counters["refused_bad_key"] == 1
    assert pb.Result.FromString(speech("asr", asr.id, "s", 1, "x")).instance == asr.id


def test_refusals_are_logged_the_first_and_every_100th(orch, component, http, caplog):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    caplog.set_level(logging.WARNING, logger="esiaf_services.orchestrator.planes.ingest")
    for i in range(250):
        asr.push.send_multipart([b"result", speech("asr", asr.id, "s", i, "no key")])
    asr.send_result(stream_id="marker")  # after them on the same socket
    wait_until(lambda: stored_texts(http, "marker"), what="the marker")
    lines = [r.getMessage() for r in caplog.records if "reason=no_key" in r.getMessage()]
    assert [re.search(r"count=(\d+)", line).group(1) for line in lines] == ["1", "100", "200"]
    assert "control_key" not in " ".join(lines) and asr.registration["control_key"] not in caplog.text

"""Registration over HTTP: register, list, delete, conflicts, bad bodies, takeover, topics."""
from __future__ import annotations

import httpx
import pytest

from esiaf.proto import esiaf_pb2 as pb
from esiaf_services.orchestrator.tests.helpers import FMT16, component_body, wait_until

FMT16_STEREO = {**FMT16, "channels": 2}
FMT48_FLOAT = {"sample_rate_hz": 48000, "sample_type": "float32", "endianness": "little",
               "channels": 1}


def test_health(http):
    assert http.get("/health").json() == {"status": "ok"}


def test_register_list_delete(orch, http):
    grabber = http.post("/components", json=component_body(
        "grabber", outputs=["audio/raw"], endpoint="tcp://127.0.0.1:40100"))
    assert grabber.status_code == 201, grabber.text
    vad = http.post("/components", json=component_body(
        "vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"],
        endpoint="tcp://127.0.0.1:40123"))
    assert vad.status_code == 201, vad.text
    body = vad.json()
    assert body["component_id"].startswith("vad-")
    assert body["control_endpoint"] == orch.core.control_endpoint
    assert body["results_endpoint"] == orch.core.results_endpoint
    assert body["heartbeat_interval_s"] == 0.5 and body["dead_after_s"] == 2.5
    assert body["peers"] == {"audio/raw": ["tcp://127.0.0.1:40100"]}
    assert body["formats"] == {"audio/raw": FMT16, "vad/speech": FMT16}

    listed = http.get("/components").json()["items"]
    assert [(c["name"], c["status"]) for c in listed] == [("grabber", "alive"), ("vad", "alive")]
    assert listed[1]["inputs"] == [{"topic": "audio/raw", "format": FMT16}]

    assert http.delete(f"/components/{body['component_id']}").status_code == 204
    assert [c["name"] for c in http.get("/components").json()["items"]] == ["grabber"]
    again = http.delete(f"/components/{body['component_id']}")
    assert again.status_code == 404 and body["component_id"] in again.json()["detail"]
    # a clean removal is not a death: it is not listed as dead either
    everyone = http.get("/components", params={"include_dead": "true"}).json()["items"]
    assert [c["name"] for c in everyone] == ["grabber"]


def test_topics_list_declared_and_assigned_formats_bytes_per_second_and_conversions(http):
    asr = http.post("/components", json=component_body(
        "asr", kind="speech", inputs=["vad/speech"], fmt=FMT16)).json()
    assert asr["formats"] == {"vad/speech": FMT16} and asr["peers"] == {"vad/speech": []}
    http.post("/components", json=component_body(
        "vad", kind="vad", outputs=["vad/speech"], fmt=FMT48_FLOAT,
        endpoint="tcp://127.0.0.1:40200"))
    topic = {t["topic"]: t for t in http.get("/topics").json()["items"]}["vad/speech"]
    # one conversion either way: min_conversions breaks the tie by bandwidth
    assert topic["format"] == FMT16 and topic["strategy"] == "min_conversions"
    assert topic["bytes_per_second"] == 32000 and topic["conversions"] == 1
    assert [(p["name"], p["format"], p["converts"]) for p in topic["producers"]] == [
        ("vad", FMT48_FLOAT, True)]
    assert [(c["name"], c["format"], c["converts"]) for c in topic["consumers"]] == [
        ("asr", FMT16, False)]
    assert topic["producers"][0]["subscribers"] is None  # nothing reported yet


def test_channel_mismatch_is_409_naming_topic_and_formats(http):
    assert http.post("/components", json=component_body(
        "grabber", outputs=["audio/raw"], fmt=FMT16_STEREO)).status_code == 201
    response = http.post("/components", json=component_body(
        "vad", kind="vad", inputs=["audio/raw"], fmt=FMT16))
    assert response.status_code == 409
    detail = response.json()["detail"]
    assert "'audio/raw'" in detail
    assert "16000 Hz int16 little-endian 1 ch" in detail
    assert "16000 Hz int16 little-endian 2 ch" in detail
    assert [c["name"] for c in http.get("/components").json()["items"]] == ["grabber"]


@pytest.mark.parametrize("change, complaint", [
    ({"name": ""}, "name"),
    ({"kind": "Not a kind!"}, "kind"),  # any name like "rate" is a kind
    ({"inputs": [{"topic": "a", "format": {**FMT16, "sample_type": "int12"}}]}, "sample_type"),
    ({"inputs": [{"topic": "a", "format": {**FMT16, "channels": 0}}]}, "channels"),
    ({"inputs": [{"topic": "a", "format": FMT16}, {"topic": "a", "format": FMT16}]},
     "more than once"),
    ({"outputs": [{"topic": "b", "format": FMT16}], "audio_endpoint": None}, "audio_endpoint"),
    ({"surprise": 1}, "surprise"),
])
def test_bad_body_is_422(http, change, complaint):
    body = {**component_body("vad", kind="vad", inputs=["audio/raw"]), **change}
    response = http.post("/components", json=body)
    assert response.status_code == 422
    assert complaint in response.text


def test_designation_the_old_name_of_kind_is_accepted_and_answered(http, caplog):
    body = component_body("vad", kind="vad", inputs=["audio/raw"])
    old = {**{k: v for k, v in body.items() if k != "kind"}, "designation": "vad"}
    assert http.post("/components", json={**body, "designation": "vad"}).status_code == 422  # not both
    with caplog.at_level("WARNING"):
        assert http.post("/components", json=old).status_code == 201
    assert "field=designation" in caplog.text
    [listed] = http.get("/components").json()["items"]
    assert listed["kind"] == listed["designation"] == "vad"


def test_bad_queries_are_422(http):
    assert http.get("/results", params={"type": "Speech!"}).status_code == 422  # not a kind name
    response = http.get("/fused", params={"start_ns": 5, "end_ns": 1})
    assert response.status_code == 422 and "start_ns" in response.json()["detail"]
    assert http.get("/fused", params={"limit": 0}).status_code == 422


def test_instances_of_a_name_share_it_a_live_id_is_409_and_a_process_registers_itself_again(component, http):
    body = component_body("asr", kind="speech", inputs=["vad/speech"])
    first = component("asr", kind="speech", inputs=["vad/speech"], instance="asr-a", incarnation="p1")
    second = component("asr", kind="speech", inputs=["vad/speech"])
    assert first.id == "asr-a" and second.id.startswith("asr-") and second.id != first.id
    listed = http.get("/components").json()
    assert [c["component_id"] for c in listed["items"]] == ["asr-a", second.id]
    assert listed["services"]["asr"]["instances"] == ["asr-a", second.id]

    for incarnation in ({"incarnation": "p2"}, {}):  # another process holds asr-a: refused, never replaced
        response = http.post("/components", json={**body, "instance": "asr-a", **incarnation})
        assert response.status_code == 409 and "'asr-a' is held by a live instance" in response.json()["detail"]
        assert response.headers["retry-after"] == "3"  # dead_after_s 2.5, rounded up
    first.heartbeat()
    assert first.recv()["type"] == "state"  # still itself

    again = http.post("/components", json={**body, "instance": "asr-a", "incarnation": "p1"})  # its own process
    assert again.status_code == 201 and again.json()["component_id"] == "asr-a"
    everyone = http.get("/components", params={"include_dead": True}).json()["items"]
    assert sorted((c["component_id"], c["status"]) for c in everyone) == sorted([("asr-a", "alive"),
                                                                               (second.id, "alive")])


def test_replicas_are_told_the_streams_they_serve(component, http):
    vad = component("vad", kind="vad", inputs=["raw"], outputs=["vad/speech"])
    a = component("asr", kind="speech", inputs=["vad/speech"], instance="asr-a")
    assert a.registration["streams"] is None and vad.registration["streams"] is None  # alone: every stream
    b = component("asr", kind="speech", inputs=["vad/speech"], instance="asr-b")
    assert b.registration["streams"] == []
    for stream in ("robot1", "robot2"):
        assert http.put(f"/streams/{stream}", json={"start_ns": 1, "source": "grabber-1"}).status_code == 200
    told = {c.id: c.wait_for(lambda m: m.get("streams"), heartbeat_every_s=0.2)["streams"] for c in (a, b)}
    assert sorted(told.values()) == [["robot1"], ["robot2"]]
    assert http.get("/components").json()["services"]["asr"]["serving"] == {
        stream: instance for instance, streams in told.items() for stream in streams}
    b.close()  # leaves without a word: declared dead, its stream moves to a
    a.wait_for(lambda m: m.get("type") == "state" and "streams" not in m, timeout_s=6, heartbeat_every_s=0.3)
    assert http.get("/components").json()["services"]["asr"] == {
        "instances": ["asr-a"], "serving": {"robot1": "asr-a", "robot2": "asr-a"}}


def test_a_component_reported_dead_is_dead_at_once_and_its_streams_move(component, http):
    a = component("asr", kind="speech", inputs=["vad/speech"], instance="asr-a")
    b = component("asr", kind="speech", inputs=["vad/speech"], instance="asr-b")
    for stream in ("robot1", "robot2"):
        assert http.put(f"/streams/{stream}", json={"start_ns": 1, "source": "grabber-1"}).status_code == 200
    assert set(http.get("/components").json()["services"]["asr"]["serving"].values()) == {"asr-a", "asr-b"}
    assert http.post("/components/asr-b/dead").status_code == 204  # its launcher saw its process die
    listed = {c["component_id"]: c["status"] for c in
              http.get("/components", params={"include_dead": True}).json()["items"]}
    assert listed["asr-b"] == "dead" and listed["asr-a"] == "alive"
    assert http.get("/components").json()["services"]["asr"]["serving"] == {"robot1": "asr-a", "robot2": "asr-a"}
    again = http.post("/components/asr-b/dead")
    assert again.status_code == 404 and "asr-b" in again.json()["detail"]
    b.close()
    a.close()


def test_fusions_listed(http):
    assert http.get("/fusions").json() == {
        "items": [{"name": "speech", "anchor": "speech", "fuse": ["ssl", "emotion", "gender", "voice_id"],
                   "stream": None}]}


def test_fusions_are_replaced_over_rest_and_bad_ones_refused(component, http):
    new = {"items": [{"name": "u", "anchor": "speech", "fuse": ["ssl"], "stream": None},
                     {"name": "v", "anchor": "vad", "fuse": [], "stream": "r1"}]}
    assert http.put("/fusions", json=new).json() == new
    assert http.get("/fusions").json() == new
    for items, complaint in (([new["items"][0]] * 2, "unique"),
                             ([{"name": "w", "anchor": "ssl", "fuse": ["ssl"]}], "cannot also be fused"),
                             ([{"name": "w", "anchor": "Speech!"}], "anchor")):
        response = http.put("/fusions", json={"items": items})
        assert response.status_code == 422 and complaint in response.text
    assert http.get("/fusions").json() == new
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    vad.send_result(stream_id="r1", type_=pb.RESULT_TYPE_VAD)
    wait_until(lambda: http.get("/fused").json()["items"], what="a fused result of fusion v")
    assert http.get("/fused").json()["items"][0]["fusion"] == "v"
    stats = http.get("/fusions/stats").json()
    assert stats["counters"]["results"] == 1 and stats["counters"]["completion_complete"] == 1
    assert stats["overhead_samples"] == 1 and stats["overhead_p50_ms"] >= 0


def test_openapi_documents_the_api(http):
    schema = http.get("/openapi.json").json()
    assert {"/components", "/components/{component_id}", "/topics", "/fused", "/results",
            "/fusions", "/health"} <= set(schema["paths"])
    fused_page = schema["paths"]["/fused"]["get"]["responses"]["200"]["content"]
    assert fused_page["application/json"]["schema"]["$ref"].endswith("/FusedPage")
    assert "RegisterRequest" in schema["components"]["schemas"]


def test_the_docs_page_needs_no_internet(http):
    """/docs and /redoc load their scripts and styles from the orchestrator itself, not a CDN."""
    import re
    for page in ("/docs", "/redoc"):
        html = http.get(page).text
        assets = re.findall(r"""(?:src|href)=["']([^"']+)["']|url: ["']([^"']+)["']""", html)
        urls = [a or b for a, b in assets]
        assert urls, html
        for url in urls:
            assert not url.startswith(("http://", "https://", "//")), f"{page} loads {url} from outside"
            assert http.get(url).status_code == 200, url


def test_streams_are_announced_listed_and_kept_across_restarts(make_orchestrator, tmp_path):
    db = str(tmp_path / "streams.db")
    first = make_orchestrator(db_path=db)
    with httpx.Client(base_url=first.url, timeout=5.0) as http:
        assert http.get("/streams/robot-1").status_code == 404
        put = http.put("/streams/robot-1", json={"start_ns": 1_700_000_000_000_000_000, "source": "grabber",
                                                 "info": {"input": "a.wav"}})
        assert put.status_code == 200, put.text
        assert put.json()["start_ns"] == 1_700_000_000_000_000_000
        again = http.put("/streams/robot-1", json={"start_ns": 1_700_000_000_500_000_000})
        assert again.json()["start_ns"] == 1_700_000_000_500_000_000 and again.json()["source"] == ""
        assert [s["stream_id"] for s in http.get("/streams").json()["items"]] == ["robot-1"]
        assert http.put("/streams/robot-2", json={"start_ns": -5}).status_code == 422
        assert http.put("/streams/robot-2", json={"start_ns": 5, "colour": "red"}).status_code == 422
    first.stop()
    with httpx.Client(base_url=make_orchestrator(db_path=db).url, timeout=5.0) as http:  # same database
        assert http.get("/streams/robot-1").json()["start_ns"] == 1_700_000_000_500_000_000

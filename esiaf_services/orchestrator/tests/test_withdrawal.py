"""A fused result sent as a person's and revised into the robot's own voice is withdrawn from the clients
that leave the robot out (real orchestrator process, real ZeroMQ results plane, real websockets): live, on
resuming with after_seq, and in GET /fused; clients that include the robot get the revision itself."""
from __future__ import annotations

import json

import zmq
from websockets.sync.client import connect

from esiaf.results import playback
from esiaf.tools.testing import Orchestrator
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body

S = 1_000_000_000
SAID = "The kitchen is on your left, next to the big window."


def frame(azimuth: float, source_id: str, background: bool) -> dict:
    return {"azimuth_deg": azimuth, "probability": 0.9, "source_id": source_id, "background": background}


def test_a_person_revised_into_the_robot_is_withdrawn(tmp_path):
    running = Orchestrator(tmp_path)
    ctx = zmq.Context()
    try:
        parts = {name: FakeComponent(ctx, running.http, component_body(name, kind=kind))
                 for name, kind in (("asr", "speech"), ("ssl", "ssl"), ("player", "playback"))}
        for part in parts.values():
            part.heartbeat()
        parts["player"].emit("playback", (1 * S, 6 * S), generic=playback(f"say: {SAID}", item=1, stopped=False))
        # the localiser: the robot (self) and a talker on a track of its own: a person
        parts["ssl"].emit("ssl", (1 * S, 3 * S), ssl={"directions": [frame(0.0, "self", True)]})
        parts["ssl"].emit("ssl", (2 * S, 3 * S), ssl={"directions": [frame(90.0, "s2", False)]})
        with connect(f"{running.ws_url}/ws/fused") as plain, \
                connect(f"{running.ws_url}/ws/fused?include_robot=true") as everything:
            parts["asr"].send_result(start_ns=2 * S, end_ns=3 * S, text="the kitchen is on your left")
            first = json.loads(plain.recv(timeout=10))
            assert (first["type"], first["revision"], first["source"]) == ("fused_result", 1, "person")
            assert json.loads(everything.recv(timeout=10))["source"] == "person"
            # later: the talker's track turns out to be the robot's reflection (background): the robot's own voice
            parts["ssl"].emit("ssl", (2 * S, 3 * S), ssl={"directions": [frame(90.0, "s2", True)]})
            withdrawn = json.loads(plain.recv(timeout=10))
            revised = json.loads(everything.recv(timeout=10))
        assert (revised["type"], revised["id"], revised["revision"], revised["source"]) == \
            ("fused_result", first["id"], 2, "robot")
        assert withdrawn == {"type": "fused_withdrawn", "id": first["id"], "revision": 2, "seq": revised["seq"],
                             "fusion": first["fusion"], "stream_id": "default", "source": "robot"}
        # resuming from before it: the person's revision, then its withdrawal; GET /fused has neither
        with connect(f"{running.ws_url}/ws/fused?after_seq=0") as resumed:
            assert [json.loads(resumed.recv(timeout=10))["type"] for _ in range(2)] == \
                ["fused_result", "fused_withdrawn"]
        assert running.http.get("/fused").json()["items"] == []
        robots = running.http.get("/fused", params={"include_robot": "true"}).json()["items"]
        assert [(f["id"], f["revision"], f["source"]) for f in robots] == [(first["id"], 2, "robot")]
    finally:
        for part in locals().get("parts", {}).values():
            part.close()
        ctx.term()
        running.close()

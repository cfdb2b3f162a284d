"""A component's control identity is bound to its registration: a peer that holds the
token and knows a component id (GET /components lists them) but not the registration's control
key neither keeps that component alive nor gets its state, and is counted; the real component
goes on beside it; a registration again gets a new key and the old one is refused."""
from __future__ import annotations

import json
import logging
import re
import time

import httpx
import zmq

from esiaf.tools.testing import refused_control
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body, wait_until

BEAT_S, DEAD_AFTER_S = 0.2, 1.0
WRONG_KEY = "A" * 43  # as long as a real one


def forger(zctx: zmq.Context, endpoint: str, identity: str | None = None) -> zmq.Socket:
    """A DEALER on the control socket, with a component's id as its routing id (the protocol
    before results were bound to their registration) or none."""
    dealer = zctx.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    if identity is not None:
        dealer.setsockopt_string(zmq.IDENTITY, identity)
    dealer.connect(endpoint)
    return dealer


def forge(dealer: zmq.Socket, component_id: str, key: str | None) -> None:
    beat = {"type": "heartbeat", "component_id": component_id, "stats": {"results_sent": 999}}
    if key is not None:
        beat["control_key"] = key
    dealer.send(json.dumps(beat).encode())


def drain(dealer: zmq.Socket) -> list[dict]:
    received = []
    while dealer.poll(0):
        received.append(json.loads(dealer.recv()))
    return received


def listed(http: httpx.Client) -> dict[str, dict]:
    return {c["component_id"]: c for c in http.get("/components", params={"include_dead": True}).json()["items"]}


def test_forged_heartbeats_do_not_keep_a_killed_component_alive(make_orchestrator, zctx):
    orch = make_orchestrator(heartbeat_interval_s=BEAT_S, dead_after_s=DEAD_AFTER_S)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http:
        grabber = FakeComponent(zctx, http, component_body("grabber", outputs=["audio/raw"]))
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"]))
        endpoint = listed(http)[grabber.id]["audio_endpoint"]
        vad.heartbeat()
        assert vad.recv()["peers"] == {"audio/raw": [endpoint]}
        grabber.heartbeat()
        assert grabber.recv()["type"] == "state"
        grabber.close()  # killed: its last message was the heartbeat above
        killed = time.monotonic()
        forgers = [(forger(zctx, orch.core.control_endpoint, grabber.id), None),
                   (forger(zctx, orch.core.control_endpoint), WRONG_KEY)]
        got: list[dict] = []
        dead_after = None
        while time.monotonic() - killed < DEAD_AFTER_S + 2.0:
            for dealer, key in forgers:
                forge(dealer, grabber.id, key)
                got += drain(dealer)
            vad.heartbeat()
            answer = vad.recv(0.05)
            if answer is not None and answer.get("peers") == {"audio/raw": []}:
                dead_after = time.monotonic() - killed
                break
        assert dead_after is not None, "the forged heartbeats kept the killed grabber alive"
        assert dead_after < DEAD_AFTER_S + 1.0  # dead on time (a loaded machine may be late by some)
        assert listed(http)[grabber.id]["status"] == "dead"
        assert listed(http)[grabber.id]["heartbeats"] == 1
        for dealer, _ in forgers:
            got += drain(dealer)
        assert [m for m in got if m.get("type") != "unknown"] == []  # no state; "unknown" once it is dead
        metrics = http.get("/metrics").text
        assert refused_control(metrics, "no_key") >= 1 and refused_control(metrics, "wrong_key") >= 1


def test_the_real_component_keeps_working_beside_a_forger(make_orchestrator, zctx):
    orch = make_orchestrator(heartbeat_interval_s=BEAT_S, dead_after_s=DEAD_AFTER_S)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http:
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"]))
        vad.heartbeat()
        assert vad.recv()["peers"] == {"audio/raw": []}
        forgers = [(forger(zctx, orch.core.control_endpoint, vad.id), WRONG_KEY),
                   (forger(zctx, orch.core.control_endpoint), None)]
        for dealer, key in forgers:  # connected and beating before the state changes
            forge(dealer, vad.id, key)
        wait_until(lambda: refused_control(http.get("/metrics").text) >= 2, what="the forgeries refused")
        grabber = FakeComponent(zctx, http, component_body("grabber", outputs=["audio/raw"]))
        endpoint = listed(http)[grabber.id]["audio_endpoint"]
        # the new peer is pushed to the vad at once, not to a forger, with no heartbeat of its own
        assert vad.wait_for(lambda m: m.get("type") == "state", timeout_s=2.0)["peers"] == {"audio/raw": [endpoint]}
        beats, got = 1, []
        start = time.monotonic()
        while time.monotonic() - start < DEAD_AFTER_S * 2.5:  # longer than anyone lives unheard
            for dealer, key in forgers:
                forge(dealer, vad.id, key)
                got += drain(dealer)
            vad.heartbeat()
            grabber.heartbeat()
            beats += 1
            assert vad.recv(BEAT_S)["type"] == "state"
            drain(grabber.dealer)
        assert got == []
        vad_now = listed(http)[vad.id]
        assert vad_now["status"] == "alive" and vad_now["heartbeats"] == beats
        assert vad_now["stats"]["results_sent"] == 0  # the forgers' stats were never taken


def test_a_registration_again_gets_a_new_key_and_the_old_one_is_refused(http, zctx):
    body = component_body("asr", kind="speech", inputs=["vad/speech"], instance="asr-a", incarnation="p1")
    first = FakeComponent(zctx, http, body)
    first.heartbeat()
    assert first.recv()["type"] == "state"
    again = FakeComponent(zctx, http, body)  # the same process registering again: it replaces itself
    assert again.id == first.id == "asr-a"
    assert again.registration["control_key"] != first.registration["control_key"]
    first.heartbeat()  # the old registration's key, on the connection that proved it before
    assert first.recv(0.5) is None
    wait_until(lambda: refused_control(http.get("/metrics").text, "wrong_key") == 1, what="the old key refused")
    again.heartbeat()
    assert again.recv()["type"] == "state"
    assert [c["heartbeats"] for c in http.get("/components").json()["items"]] == [1]
    first.close()
    again.close()


def test_refusals_are_logged_the_first_and_every_100th(orch, http, zctx, caplog):
    caplog.set_level(logging.WARNING, logger="esiaf_services.orchestrator.planes.control")
    vad = FakeComponent(zctx, http, component_body("vad", kind="vad", inputs=["audio/raw"]))
    dealer = forger(zctx, orch.core.control_endpoint)
    for _ in range(250):
        forge(dealer, vad.id, None)
    wait_until(lambda: refused_control(http.get("/metrics").text, "no_key") == 250, what="250 refusals")
    logged = [re.search(r"reason=(\S+) component_id=(\S+) count=(\d+)", r.getMessage()) for r in caplog.records
              if "event=control_refused" in r.getMessage()]
    assert [m.groups() if m else None for m in logged] == [("no_key", vad.id, str(n)) for n in (1, 100, 200)]
    assert drain(dealer) == []
    vad.close()

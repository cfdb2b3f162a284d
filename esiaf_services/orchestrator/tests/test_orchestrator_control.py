"""The control plane over real DEALER sockets: heartbeats, state pushes, deaths."""
from __future__ import annotations

import time

import zmq

from esiaf_services.orchestrator.tests.helpers import FMT16


def peers_are(topic: str, endpoints: list[str]):
    return lambda m: m.get("type") == "state" and m["peers"].get(topic) == endpoints


def test_heartbeat_is_answered_with_full_state_and_stats_are_kept(component, http):
    grabber = component("grabber", outputs=["audio/raw"], endpoint="tcp://127.0.0.1:40444")
    vad = component("vad", kind="vad", inputs=["audio/raw"], outputs=["vad/speech"])
    vad.heartbeat()
    assert vad.recv() == {"type": "state", "peers": {"audio/raw": ["tcp://127.0.0.1:40444"]},
                          "formats": {"audio/raw": FMT16, "vad/speech": FMT16}, "version": 1,
                          "consumers": []}  # it has outputs: who takes them (nobody yet)
    grabber.heartbeat({"inputs": {}, "outputs": {"audio/raw": {"published": 12, "subscribers": 1}},
                       "results_sent": 0, "info": {}})
    assert grabber.recv()["type"] == "state"
    listed = {c["name"]: c for c in http.get("/components").json()["items"]}
    assert listed["grabber"]["heartbeats"] == 1
    assert listed["grabber"]["stats"]["outputs"]["audio/raw"]["published"] == 12
    topic = http.get("/topics").json()["items"][0]
    assert topic["topic"] == "audio/raw" and topic["producers"][0]["subscribers"] == 1


def test_unknown_component_is_told_so(orch, zctx):
    dealer = zctx.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.setsockopt_string(zmq.IDENTITY, "ghost-000000")
    dealer.connect(orch.core.control_endpoint)
    dealer.send_json({"type": "heartbeat", "component_id": "ghost-000000", "stats": {}})
    assert dealer.poll(5000), "no answer to an unknown component's heartbeat"
    assert dealer.recv_json() == {"type": "unknown"}
    dealer.close(linger=0)


def test_producer_registering_after_consumer_is_pushed_to_it(component):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    assert asr.registration["peers"] == {"vad/speech": []}
    asr.heartbeat()  # the DEALER is connected once it has an answer
    assert asr.recv()["peers"] == {"vad/speech": []}
    vad = component("vad", kind="vad", outputs=["vad/speech"],
                    endpoint="tcp://127.0.0.1:40555")
    # no heartbeat from asr: the new peer must be pushed at once
    pushed = asr.wait_for(lambda m: m.get("type") == "state", timeout_s=2.0)
    assert pushed == {"type": "state", "peers": {"vad/speech": ["tcp://127.0.0.1:40555"]},
                      "formats": {"vad/speech": FMT16}, "version": 2}
    assert vad.registration["formats"] == {"vad/speech": FMT16}


def test_removed_producer_is_withdrawn_from_consumer(component, http):
    grabber = component("grabber", outputs=["audio/raw"], endpoint="tcp://127.0.0.1:40666")
    vad = component("vad", kind="vad", inputs=["audio/raw"])
    vad.heartbeat()
    assert vad.recv()["peers"] == {"audio/raw": ["tcp://127.0.0.1:40666"]}
    assert http.delete(f"/components/{grabber.id}").status_code == 204
    vad.wait_for(peers_are("audio/raw", []), timeout_s=2.0)


def test_heartbeats_keep_alive_and_silence_kills_within_3_s(component, http):
    grabber = component("grabber", outputs=["audio/raw"], endpoint="tcp://127.0.0.1:40777")
    vad = component("vad", kind="vad", inputs=["audio/raw"])
    # Both beat for longer than dead_after_s (2.5 s): nobody dies.
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        grabber.keep_alive(0.25, every_s=0.5)
        vad.keep_alive(0.25, every_s=0.5)
    assert {c["name"] for c in http.get("/components").json()["items"]} == {"grabber", "vad"}

    grabber.heartbeat()
    grabber.recv()
    silent_since = time.monotonic()  # grabber's last message
    vad.wait_for(peers_are("audio/raw", []), timeout_s=4.0, heartbeat_every_s=0.5)
    assert time.monotonic() - silent_since < 3.0
    assert [c["name"] for c in http.get("/components").json()["items"]] == ["vad"]
    everyone = {c["name"]: c for c in
                http.get("/components", params={"include_dead": True}).json()["items"]}
    assert everyone["grabber"]["status"] == "dead"
    grabber.heartbeat()
    assert grabber.wait_for(lambda m: True) == {"type": "unknown"}


def test_a_current_state_is_acknowledged_a_changed_or_missed_one_is_sent_in_full(component):
    vad = component("vad", kind="vad", inputs=["audio/raw"])
    vad.heartbeat()  # no state_version (an older SDK): always the full state
    first = vad.recv()
    assert first == {"type": "state", "peers": {"audio/raw": []}, "formats": {"audio/raw": FMT16}, "version": 1}
    vad.heartbeat(state_version=1, sent_ns=1_000)
    ack = vad.recv()
    assert ack is not None and ack.pop("orchestrator_ns") > 0
    assert ack == {"type": "ack", "version": 1, "echo_ns": 1_000}  # the clock sample, and no state
    for stale in (0, 7, True, "1"):  # none, unknown, or not a number: the full state
        vad.heartbeat(state_version=stale)
        assert vad.recv() == first
    component("grabber", outputs=["audio/raw"], endpoint="tcp://127.0.0.1:40888")
    pushed = vad.wait_for(lambda m: m.get("type") == "state", timeout_s=2.0)
    assert pushed["peers"] == {"audio/raw": ["tcp://127.0.0.1:40888"]} and pushed["version"] == 2
    vad.heartbeat(state_version=1)  # as if the push were lost: the answer carries it
    assert vad.recv() == pushed
    vad.heartbeat(state_version=2)
    assert vad.recv() == {"type": "ack", "version": 2}


def test_heartbeats_arriving_together_and_amid_pushes_are_all_answered(component):
    """The control socket is drained at each wake-up and looked at again after each send (its file
    descriptor is edge-triggered): no heartbeat waits for the next one to be answered."""
    vads = [component("vad", kind="vad", inputs=["audio/raw"]) for _ in range(12)]
    for vad in vads:
        vad.heartbeat()
        assert vad.recv()["type"] == "state"  # connected
    for round_ in range(3):
        for vad in vads:  # together: several are queued when the loop wakes
            vad.heartbeat(state_version=vad.registration.get("seen", 0))
        # a producer registering pushes a new state to every vad while their beats arrive
        component("grabber", outputs=["audio/raw"], endpoint=f"tcp://127.0.0.1:{40900 + round_}")
        for vad in vads:
            answers = [vad.recv(timeout_s=1.0), vad.recv(timeout_s=1.0)]  # its answer and the push, any order
            assert all(a is not None for a in answers), f"{vad.id}: not answered within 1 s"
            vad.registration["seen"] = max(a["version"] for a in answers if a is not None)

"""Seeded fuzzing: random and mutated frames at the orchestrator's results and control
sockets and at a component's audio input. Nothing crashes, and every valid result sent among
them is stored."""
from __future__ import annotations

import json
import random

import numpy as np
import zmq
from test_component import run_on
from test_hostile_input import forged, pair  # noqa: F401  (pair is a fixture)

from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import make_result
from esiaf.tools.testing import poll, signed_result
from esiaf.transport import topic_frame

SEED = 20261123
BASE_NS = 1_763_720_000_000_000_000


def mutate(rng: random.Random, data: bytes) -> bytes:
    """One of: random bytes, bit flips, a truncation, a splice, a repetition."""
    choice = rng.randrange(5)
    if choice == 0 or not data:
        return rng.randbytes(rng.randrange(0, 300))
    raw = bytearray(data)
    if choice == 1:
        for _ in range(rng.randrange(1, 8)):
            raw[rng.randrange(len(raw))] ^= 1 << rng.randrange(8)
        return bytes(raw)
    if choice == 2:
        return bytes(raw[:rng.randrange(len(raw))])
    if choice == 3:
        cut = rng.randrange(len(raw))
        return bytes(raw[:cut]) + rng.randbytes(rng.randrange(1, 40)) + bytes(raw[cut:])
    return bytes(raw) * rng.randrange(2, 5)


def valid_result(i: int, stream: str = "fuzz") -> pb.Result:
    return make_result("asr", "speech", stream, (BASE_NS + i * 10**9, BASE_NS + i * 10**9 + 5), i,
                       speech={"hypotheses": [{"text": f"valid {i}", "probability": 0.5}]})


def test_results_and_control_sockets_survive_10000_fuzzed_frames(orchestrator):
    rng = random.Random(SEED)
    registration = orchestrator.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
    context = zmq.Context()
    push, dealer = context.socket(zmq.PUSH), context.socket(zmq.DEALER)
    for sock in (push, dealer):
        sock.setsockopt(zmq.LINGER, 0)
    push.connect(registration["results_endpoint"])
    dealer.setsockopt_string(zmq.IDENTITY, registration["component_id"])
    dealer.connect(registration["control_endpoint"])
    valid_sent = 0
    heartbeat = json.dumps({"type": "heartbeat", "component_id": registration["component_id"],
                            "control_key": registration["control_key"], "stats": {}}).encode()
    try:
        template = valid_result(0, stream="mutant").SerializeToString()  # its mutants that still parse are not counted
        for n in range(10_000):
            if n % 20 == 0:
                valid_sent += 1
                push.send_multipart(signed_result(registration, valid_result(valid_sent)))
            kind = rng.choice([b"result", b"end_of_stream", b"", rng.randbytes(4)])
            frames = [kind, mutate(rng, template)] + [rng.randbytes(3)] * rng.choice([0, 0, 0, 1])
            push.send_multipart(frames)
            if n % 5 == 0:
                dealer.send(mutate(rng, heartbeat))
        poll(lambda: len(orchestrator.http.get("/results", params={"stream": "fuzz", "limit": 1000})
                         .json()["items"]) == valid_sent, timeout_s=60)
        assert orchestrator.process.poll() is None
        assert orchestrator.http.get("/health").status_code == 200
    finally:
        context.destroy(linger=0)


def test_a_components_audio_input_survives_fuzzed_messages(pair):  # noqa: F811
    source, sink, sink_thread = pair
    rng = random.Random(SEED)
    template = forged()

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for _ in range(3_000):
            c.context.node.transport.pub.send_multipart([topic_frame("source/audio"), mutate(rng, template)])
        c.publish("source/audio", np.zeros(320, dtype=np.int16), BASE_NS, BASE_NS + 20_000_000)

    run_on(source, send)
    poll(lambda: any(e[2] == BASE_NS for e in sink.events if e[0] == "audio"), timeout_s=60)
    assert sink_thread.is_alive()
    assert sink.input_stats["source/audio"].bad > 0

"""The SDK's heartbeat thread against a fake orchestrator (a ROUTER in the test): it gives back the
number of the state it applied, passes on a full state however it arrives (an answer or a push),
and takes an ack as life and a clock sample, not as a state (docs/protocol.md, "Control")."""
from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zmq

from esiaf import control
from esiaf.control import ControlClient, Registration
from esiaf.transport import STATE_ADDRESS

FMT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


@contextlib.contextmanager
def fake_orchestrator(monkeypatch: pytest.MonkeyPatch, **registration: Any) -> Iterator[
        tuple[zmq.Socket, zmq.Socket, ControlClient, list[Registration]]]:
    """The orchestrator's ROUTER, the data thread's end of the state PAIR, a started client and the
    registrations it made (with ``registration``'s fields)."""
    ctx = zmq.Context()
    router, states = ctx.socket(zmq.ROUTER), ctx.socket(zmq.PAIR)
    states.bind(STATE_ADDRESS)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    made: list[Registration] = []

    def register(*args: Any, **kwargs: Any) -> Registration:
        made.append(Registration(**{"component_id": "vad-1", "control_endpoint": f"tcp://127.0.0.1:{port}",
                                    "results_endpoint": "", "heartbeat_interval_s": 0.2, "dead_after_s": 5.0,
                                    "control_key": "key", **registration}))
        return made[-1]

    monkeypatch.setattr(control, "register", register)
    client = ControlClient(ctx, "http://127.0.0.1:1", {}, stats=dict, register_timeout_s=1.0)
    client.start()
    try:
        yield router, states, client, made
    finally:
        client.stop(unregister_too=False)
        router.close(linger=0)
        states.close(linger=0)
        ctx.term()


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[zmq.Socket, zmq.Socket, ControlClient]]:
    """The orchestrator's ROUTER, the data thread's end of the state PAIR, and a started client."""
    with fake_orchestrator(monkeypatch) as (router, states, client, _):
        yield router, states, client


def beat(router: zmq.Socket) -> tuple[bytes, dict[str, Any]]:
    assert router.poll(3000), "no heartbeat"
    route, data = router.recv_multipart()
    message = json.loads(data)
    assert message["type"] == "heartbeat" and message["control_key"] == "key"
    return route, message


def state(version: int, endpoint: str) -> dict[str, Any]:
    return {"type": "state", "peers": {"audio/raw": [endpoint]}, "formats": {"audio/raw": FMT}, "version": version}


def test_a_state_is_applied_as_answer_or_push_and_an_ack_is_life_only(fake):
    router, states, client = fake
    route, first = beat(router)
    assert first["state_version"] == 0  # none yet: the answer must be the full state
    router.send_multipart([route, json.dumps({**state(3, "tcp://a:1"), "echo_ns": first["sent_ns"],
                                              "orchestrator_ns": time.time_ns()}).encode()])
    assert states.poll(3000) and json.loads(states.recv())["peers"] == {"audio/raw": ["tcp://a:1"]}
    route, second = beat(router)
    assert second["state_version"] == 3 and client.clock.best is not None
    samples = len(client.clock._samples)
    router.send_multipart([route, json.dumps({"type": "ack", "version": 3, "echo_ns": second["sent_ns"],
                                              "orchestrator_ns": time.time_ns()}).encode()])
    route, third = beat(router)
    assert third["state_version"] == 3 and len(client.clock._samples) == samples + 1  # a clock sample
    assert not states.poll(0), "an ack was passed to the data thread as a state"
    router.send_multipart([route, json.dumps(state(4, "tcp://b:2")).encode()])  # a push, between beats
    assert states.poll(3000) and json.loads(states.recv())["peers"] == {"audio/raw": ["tcp://b:2"]}
    _, fourth = beat(router)
    assert fourth["state_version"] == 4
    assert client.registration is not None and client.registration.peers == {"audio/raw": ["tcp://b:2"]}

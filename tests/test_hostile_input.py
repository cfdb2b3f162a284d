"""Issue 13: nothing a peer sends may kill a component or the orchestrator. Each test reproduces a
defect found against ESIAF over real sockets (a 3-byte frame killed asr, emotion and gender; a
registration with ``foo://x`` as its endpoint killed every consumer of its topic)."""
from __future__ import annotations

import numpy as np
import pytest
import zmq
from test_component import Sink, Source, run_on, start

from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.testing import poll
from esiaf.transport import Transport, topic_frame, valid_endpoint


@pytest.fixture
def pair(orchestrator):
    sink, sink_thread = start(Sink, orchestrator.url)
    poll(lambda: orchestrator.component("sink"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    yield source, sink, sink_thread
    for component, thread in ((source, source_thread), (sink, sink_thread)):
        component.stop()
        thread.join(timeout=10)


def forged(**fields) -> bytes:
    message = pb.AugmentedAudio(topic="source/audio", stream_id="s", publisher="forger", sequence=1,
                                start_ns=10**18, end_ns=10**18 + 20_000_000, payload=b"\0\0" * 320)
    message.format.sample_rate_hz, message.format.sample_type, message.format.channels = 16000, pb.SAMPLE_TYPE_INT16, 1
    for name, value in fields.items():
        if name == "rate":
            message.format.sample_rate_hz = value
        else:
            setattr(message, name, value)
    return message.SerializeToString()


HOSTILE = {
    "three bytes": [b"\x01\x02\x03"],
    "not a protobuf": [b"\xff" * 64],
    "three frames": [b"x", b"y"],
    "1 Hz audio (320 bytes as 160 s)": [forged(rate=1)],
    "half a sample": [forged(payload=b"\0\0\0")],
    "a span that ends before it starts": [forged(end_ns=10)],
    "a capture time past 2116": [forged(start_ns=2**63 - 2, end_ns=2**63 - 1)],
}


def test_hostile_frames_are_refused_counted_and_the_component_goes_on(pair, orchestrator):
    source, sink, sink_thread = pair

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for frames in HOSTILE.values():
            c._transport.pub.send_multipart([topic_frame("source/audio"), *frames])
        c.publish("source/audio", np.zeros(320, dtype=np.int16), 10**18, 10**18 + 20_000_000)

    run_on(source, send)
    poll(lambda: sink.events, timeout_s=10)
    assert sink_thread.is_alive()
    assert sink.input_stats["source/audio"].bad == len(HOSTILE)
    assert sum(sink.refused.values()) == len(HOSTILE) and sink.refused["frames"] == 1
    # the counters reach the orchestrator with the heartbeats
    poll(lambda: sum((orchestrator.component("sink")["stats"].get("refused") or {}).values()) == len(HOSTILE),
         timeout_s=10)


def test_ten_thousand_publisher_names_do_not_grow_the_component(pair):
    source, sink, _ = pair

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for i in range(10_000):
            c._transport.pub.send_multipart([topic_frame("source/audio"), forged(publisher=f"p{i}")])

    run_on(source, send)
    poll(lambda: len(sink.events) == 10_000, timeout_s=60)
    assert len(sink._receiver.links) <= 256 and len(sink._receiver.last_seen) <= 256


@pytest.mark.parametrize("endpoint", ["foo://x", "tcp://", "tcp://host:99999", "ipc:///tmp/x", 7])
def test_a_bad_endpoint_is_never_connected_and_never_fatal(endpoint):
    assert not valid_endpoint(endpoint)
    context = zmq.Context()
    transport = Transport(context, inputs=["t"], has_outputs=False, bind_host="127.0.0.1")
    try:
        transport.connect_peers({endpoint, "tcp://127.0.0.1:1"})
        assert transport._connected == {"tcp://127.0.0.1:1"}
    finally:
        transport.close()
        context.term()


@pytest.mark.parametrize("endpoint", ["foo://x", "tcp://127.0.0.1:0", "tcp://127.0.0.1:70000", "tcp://a b:1"])
def test_a_registration_with_a_bad_endpoint_gets_422_naming_the_field(orchestrator, endpoint):
    body = {"name": "forger", "designation": "other", "audio_endpoint": endpoint,
            "outputs": [{"topic": "vad/speech", "format": {"sample_rate_hz": 16000, "sample_type": "int16",
                                                           "channels": 1}}]}
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 422
    assert "audio_endpoint" in response.text


def test_oversized_registrations_are_refused(orchestrator):
    body = {"name": "big", "designation": "other", "info": {"blob": "x" * 100_000}}
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 422 and "info is" in response.text
    body["info"] = {"blob": "x" * 50_000_000}  # 50 MB: refused before it is parsed
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 413 and "max_body_bytes" in response.text
    assert orchestrator.http.get("/health").status_code == 200


def test_numpy_numbers_in_info_travel_with_heartbeats_and_the_component_stays_registered(pair, orchestrator):
    # issue 14: a numpy float in self.info killed the heartbeat thread; the component ran on unregistered
    _source, sink, sink_thread = pair
    sink.info.update(peak=np.float32(0.5), levels=np.array([1, 2]))
    sink.control.poke()
    info = poll(lambda: orchestrator.component("sink")["stats"]["info"].get("levels") and
                orchestrator.component("sink")["stats"]["info"], timeout_s=10)
    assert info["peak"] == 0.5 and info["levels"] == [1, 2]
    assert sink.control._thread.is_alive() and sink_thread.is_alive()

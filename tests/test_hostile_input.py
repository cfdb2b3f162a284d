"""Nothing a peer sends may kill a component or the orchestrator. Each test reproduces a
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
            c.context.node.transport.pub.send_multipart([topic_frame("source/audio"), *frames])
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
            c.context.node.transport.pub.send_multipart([topic_frame("source/audio"), forged(publisher=f"p{i}")])

    run_on(source, send)
    poll(lambda: len(sink.events) == 10_000, timeout_s=60)
    assert len(sink.context.receiver.links) <= 256 and len(sink.context.receiver.last_seen) <= 256


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
    body = {"name": "forger", "kind": "other", "audio_endpoint": endpoint,
            "outputs": [{"topic": "vad/speech", "format": {"sample_rate_hz": 16000, "sample_type": "int16",
                                                           "channels": 1}}]}
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 422
    assert "audio_endpoint" in response.text


def test_oversized_registrations_are_refused(orchestrator):
    body = {"name": "big", "kind": "other", "info": {"blob": "x" * 100_000}}
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 422 and "info is" in response.text
    body["info"] = {"blob": "x" * 50_000_000}  # 50 MB: refused before it is parsed
    response = orchestrator.http.post("/components", json=body)
    assert response.status_code == 413 and "max_body_bytes" in response.text
    assert orchestrator.http.get("/health").status_code == 200


def test_numpy_numbers_in_info_travel_with_heartbeats_and_the_component_stays_registered(pair, orchestrator):
    # a numpy float in self.info once killed the heartbeat thread; the component ran on unregistered
    _source, sink, sink_thread = pair
    sink.info.update(peak=np.float32(0.5), levels=np.array([1, 2]))
    sink.control.poke()
    info = poll(lambda: orchestrator.component("sink")["stats"]["info"].get("levels") and
                orchestrator.component("sink")["stats"]["info"], timeout_s=10)
    assert info["peak"] == 0.5 and info["levels"] == [1, 2]
    assert sink.control._thread.is_alive() and sink_thread.is_alive()


def test_four_hundred_stream_names_do_not_grow_the_vad_and_a_real_stream_is_still_segmented(orchestrator):
    """Per-stream state is bounded (esiaf/per_stream.py): a peer naming a new stream in every message
    makes the vad forget the least recently heard streams' segmenters, counted, and a stream heard
    all along is segmented as if alone."""
    from esiaf_services.vad.service import Vad
    vad, vad_thread = start(Vad, orchestrator.url, input_topic="source/audio", backend="energy", max_streams=16)
    poll(lambda: orchestrator.component("vad"), timeout_s=30)
    source, source_thread = start(Source, orchestrator.url)
    chunk_ns, loud = 50_000_000, (0.5 * 32767 * np.sin(np.arange(800) * 0.3)).astype(np.int16)

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for i in range(40):  # 1 s loud, 1 s silent; between two of its chunks, 10 streams never heard again
            start_ns = 10**18 + i * chunk_ns
            c.publish("source/audio", loud if i < 20 else np.zeros(800, np.int16), start_ns, start_ns + chunk_ns,
                      stream_id="real")
            for j in range(10):
                c.publish("source/audio", np.zeros(800, np.int16), start_ns, start_ns + chunk_ns,
                          stream_id=f"forged-{i}-{j}")

    try:
        run_on(source, send)
        poll(lambda: vad.input_stats["source/audio"].received == 440, timeout_s=30)
        assert vad_thread.is_alive()
        assert len(vad.segmenters) == 16 and "real" in vad.segmenters
        assert vad.segmenters.forgotten == 400 - 15 and vad.info["forgotten_streams"] == 385
        assert vad.segments == 1  # the real stream's one second of sound, ended by its silence
        poll(lambda: orchestrator.component("vad")["stats"]["info"].get("forgotten_streams") == 385, timeout_s=10)
    finally:
        for component, thread in ((source, source_thread), (vad, vad_thread)):
            component.stop()
            thread.join(timeout=10)


def test_a_segment_that_never_ends_keeps_only_its_last_max_utterance_s(orchestrator):
    """An utterance analyser buffers an open segment until its end: a peer that never ends one must not
    grow it without bound. Past max_utterance_s its start is dropped and counted (trimmed_s)."""
    from esiaf import UtteranceComponent

    sizes: list[int] = []  # of the samples each analyse() was given

    class Duration(UtteranceComponent):
        service = kind = "duration"

        def analyse(self, samples, rate):
            sizes.append(samples.size)
            return {"value": samples.size / rate}

    analyser, analyser_thread = start(Duration, orchestrator.url, input_topic="source/audio", max_utterance_s=1.0)
    poll(lambda: orchestrator.component("duration"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    chunk_ns, sound = 50_000_000, (0.3 * 32767 * np.sin(np.arange(800) * 0.3)).astype(np.int16)

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for i in range(60):  # 3 s of one segment, then its end
            c.publish("source/audio", sound, i * chunk_ns, (i + 1) * chunk_ns, stream_id="long",
                      segmentation_ended=i == 59, segment=(0, 60 * chunk_ns) if i == 59 else None)

    try:
        run_on(source, send)
        poll(lambda: sizes, timeout_s=10)
        assert sizes == [16_000]  # its last second
        assert analyser.info["trimmed_s"] == pytest.approx(2.0) and len(analyser.utterances) == 0
    finally:
        for component, thread in ((source, source_thread), (analyser, analyser_thread)):
            component.stop()
            thread.join(timeout=10)


def test_streams_ended_on_one_input_of_two_are_remembered_within_max_streams(orchestrator):
    """A component with two inputs ends a stream once both have ended it; streams ended on one input
    only (a peer naming a new stream per message) are remembered for the most recent max_streams."""
    from esiaf import AudioFormat, Component

    class TwoInputs(Component):
        service = "twoinputs"

        def __init__(self, settings):
            super().__init__(settings)
            self.add_input("source/audio", AudioFormat(16000, "int16"))
            self.add_input("other/audio", AudioFormat(16000, "int16"))

    sink, sink_thread = start(TwoInputs, orchestrator.url, max_streams=8)
    poll(lambda: orchestrator.component("twoinputs"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for i in range(50):
            c.publish("source/audio", np.zeros(160, np.int16), 10**18, 10**18 + 10_000_000, stream_id=f"s{i}",
                      end_of_stream=True)

    try:
        run_on(source, send)
        poll(lambda: sink.input_stats["source/audio"].received == 50, timeout_s=10)
        assert len(sink.context.ended) == 8 and sink.info["forgotten_streams"] == 42
    finally:
        for component, thread in ((source, source_thread), (sink, sink_thread)):
            component.stop()
            thread.join(timeout=10)

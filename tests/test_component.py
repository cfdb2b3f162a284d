"""The SDK over real ZeroMQ sockets against the real orchestrator."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from esiaf import Audio, AudioFormat, Component, SampleClock, ssl_direction
from esiaf.links import OutputLink
from esiaf.tools.testing import REPO, poll

FMT = AudioFormat(16000, "int16")


class Source(Component):
    service = "source"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("source/audio", FMT)
        self.script = []  # callables run by produce(), in order, whenever they are added

    def produce(self):
        while not self.stopping:
            while self.script:
                self.script.pop(0)(self)
            self.sleep_until(time.monotonic() + 0.05)


class Sink(Component):
    service = "sink"
    kind = "vad"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_input("source/audio", FMT)
        self.events = []
        self.frames = []
        self.received = threading.Event()

    def on_audio(self, audio: Audio):
        self.events.append(("audio", audio.sequence, audio.start_ns, audio.end_ns))
        self.frames.append(audio.frames)
        self.received.set()

    def on_ssl(self, audio: Audio):
        self.events.append(("ssl", audio.sequence, audio.ssl_directions[0].azimuth_deg))

    def on_segment_end(self, audio: Audio):
        self.events.append(("segment_end", audio.sequence))
        self.emit("vad", (audio.meta.segment.start_ns, audio.meta.segment.end_ns), stream_id=audio.stream_id,
                  vad={"probability": 0.5})

    def on_end_of_stream(self, stream_id, audio):
        self.events.append(("end_of_stream", stream_id))


def start(component_cls, url, **settings):
    component = component_cls(component_cls.Settings(name=component_cls.service, orchestrator_url=url, **settings))
    thread = threading.Thread(target=component.run, daemon=True)
    thread.start()
    return component, thread


@pytest.fixture
def pair(orchestrator):
    sink, sink_thread = start(Sink, orchestrator.url)
    poll(lambda: orchestrator.component("sink"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    yield source, sink
    for component, thread in ((source, source_thread), (sink, sink_thread)):
        component.stop()
        thread.join(timeout=10)


def run_on(source, step):
    """Runs ``step`` on the source's own thread (sockets belong to one thread)."""
    done = threading.Event()
    source.script.append(lambda c: (step(c), done.set()))
    return done


def test_designation_the_old_name_of_kind_still_works_with_a_deprecation_line(caplog):
    assert Sink.designation == "vad"  # read: it is kind
    with caplog.at_level("WARNING", logger="esiaf.processor"):
        class Old(Component):
            designation = "speech"
    assert Old.kind == Old.designation == "speech" and "designation" in caplog.text
    with pytest.raises(TypeError, match="not a kind name"):
        class Bad(Component):
            kind = "Not a kind!"


def test_audio_arrives_with_capture_times_and_contiguous_sequence_numbers(pair, orchestrator):
    source, sink = pair
    clock = SampleClock(1_700_000_000_000_000_000, 16000)

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for _ in range(50):
            c.publish("source/audio", np.zeros(320, dtype=np.int16), *clock.advance(320))

    run_on(source, send)
    poll(lambda: len(sink.events) >= 50, timeout_s=10)
    assert [e[1] for e in sink.events] == list(range(1, 51))
    assert sink.events[0][2:] == (1_700_000_000_000_000_000, 1_700_000_000_020_000_000)
    assert all(a[3] == b[2] for a, b in itertools.pairwise(sink.events))
    assert sink.input_stats["source/audio"].lost == 0


def test_callback_order_and_results_carry_the_capture_span(pair, orchestrator):
    source, sink = pair

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        c.publish("source/audio", np.zeros(160, dtype=np.int16), 1000, 10_001_000, segmentation_ended=True,
                  segment=(500, 9_000_000), ssl_directions=[ssl_direction(92.0)])
        c.publish("source/audio", b"", 10_001_000, 10_001_000, end_of_stream=True)

    run_on(source, send)
    poll(lambda: len(sink.events) >= 5, timeout_s=10)
    assert [e[0] for e in sink.events] == ["audio", "ssl", "segment_end", "audio", "end_of_stream"]
    assert sink.events[1][2] == 92.0
    results = poll(lambda: orchestrator.http.get("/results", params={"type": "vad"}).json()["items"], timeout_s=10)
    assert results[0]["span"] == {"start_ns": 500, "end_ns": 9_000_000}
    assert results[0]["component"] == "sink"


def test_loss_is_counted_and_visible_in_the_orchestrator(pair, orchestrator):
    source, sink = pair

    def send_with_gap(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        c.publish("source/audio", np.zeros(160, dtype=np.int16), 0, 10_000_000)
        c.context.sequences["source/audio", c.settings.stream_id] += 3  # three messages "lost on the way"
        c.publish("source/audio", np.zeros(160, dtype=np.int16), 40_000_000, 50_000_000)

    run_on(source, send_with_gap)
    poll(lambda: len(sink.events) >= 2, timeout_s=10)
    assert sink.input_stats["source/audio"].lost == 3
    poll(lambda: orchestrator.component("sink")["stats"]["inputs"]["source/audio"]["lost"] == 3, timeout_s=5)


def test_another_rate_is_converted_another_channel_count_is_bad(pair, orchestrator):
    source, sink = pair

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        # sends what the topic was not assigned, as an older or foreign producer might
        c.context.output_links["source/audio"] = OutputLink("source/audio", AudioFormat(48000, "int16"))
        c.publish("source/audio", np.zeros(480, dtype=np.int16), 0, 10_000_000, end_of_stream=True)
        c.context.output_links["source/audio"] = OutputLink("source/audio", AudioFormat(16000, "int16", channels=2))
        c.publish("source/audio", np.zeros((160, 2), dtype=np.int16), 10_000_000, 20_000_000)

    run_on(source, send)
    poll(lambda: sink.input_stats["source/audio"].bad == 1, timeout_s=10)
    assert sink.events[0] == ("audio", 1, 0, 10_000_000)  # 48 kHz in, 16 kHz out, the same span
    assert sink.frames == [160] and sink.input_stats["source/audio"].received == 2


def test_a_slow_handler_does_not_make_the_component_look_dead(orchestrator):
    class Slow(Sink):
        def on_audio(self, audio):
            time.sleep(4.0)  # longer than dead_after_s: a long decode
            super().on_audio(audio)

    Slow.service = "sink"
    sink, sink_thread = start(Slow, orchestrator.url)
    source, source_thread = start(Source, orchestrator.url)
    run_on(source, lambda c: (c.wait_for_subscribers("source/audio", 1, 10),
                              c.publish("source/audio", np.zeros(160, dtype=np.int16), 0, 10_000_000)))
    assert sink.received.wait(timeout=15)
    assert orchestrator.component("sink")["status"] == "alive"
    for component, thread in ((source, source_thread), (sink, sink_thread)):
        component.stop()
        thread.join(timeout=10)


def test_a_backlog_shows_as_the_input_queue_depth_in_the_heartbeat(orchestrator):
    class Busy(Sink):
        def on_audio(self, audio):
            if audio.sequence == 1:
                time.sleep(0.5)  # the rest of the burst waits behind the first message
            super().on_audio(audio)

    Busy.service = "sink"
    sink, sink_thread = start(Busy, orchestrator.url)
    source, source_thread = start(Source, orchestrator.url)

    def queued():
        return orchestrator.component("sink")["stats"]["inputs"]["source/audio"]["queued"]

    try:
        poll(lambda: orchestrator.component("sink") and orchestrator.component("sink").get("stats"), timeout_s=10)
        assert queued() == 0
        run_on(source, lambda c: (c.wait_for_subscribers("source/audio", 1, 10),
                                  [c.publish("source/audio", np.zeros(160, dtype=np.int16), i * 10_000_000,
                                             (i + 1) * 10_000_000) for i in range(20)]))
        poll(lambda: len(sink.events) == 20, timeout_s=10)
        poll(lambda: queued() >= 10, timeout_s=5, interval_s=0.02)  # 19 at most, less what came in later
        poll(lambda: queued() == 0, timeout_s=5)  # caught up: the next heartbeat says so
    finally:
        for component, thread in ((source, source_thread), (sink, sink_thread)):
            component.stop()
            thread.join(timeout=10)


def test_sigterm_stops_a_service_cleanly_and_unregisters_it(orchestrator):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    vad = subprocess.Popen([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    poll(lambda: orchestrator.component("vad"), timeout_s=30)
    vad.send_signal(signal.SIGTERM)
    assert vad.wait(timeout=10) == 0, vad.stderr.read()
    poll(lambda: orchestrator.component("vad") is None or orchestrator.component("vad")["status"] != "alive",
         timeout_s=5)


def test_a_killed_component_is_dead_within_3_s(orchestrator):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    vad = subprocess.Popen([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    poll(lambda: orchestrator.component("vad"), timeout_s=30)
    vad.kill()
    vad.wait()
    killed = time.monotonic()
    poll(lambda: (orchestrator.component("vad") or {"status": "dead"})["status"] != "alive", timeout_s=5,
         interval_s=0.02)
    assert time.monotonic() - killed <= 3.0


class Splitter(Component):
    """Publishes every received chunk as two halves: two publishes inside one handler."""
    service = "splitter"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_input("source/audio", FMT)
        self.add_output("splitter/audio", FMT)

    def on_audio(self, audio: Audio):
        middle_ns = (audio.start_ns + audio.end_ns) // 2
        half = len(audio.payload) // 2
        self.publish("splitter/audio", audio.payload[:half], audio.start_ns, middle_ns, stream_id=audio.stream_id)
        self.publish("splitter/audio", audio.payload[half:], middle_ns, audio.end_ns, stream_id=audio.stream_id)


class SplitSink(Sink):
    service = "splitsink"

    def __init__(self, settings):
        Component.__init__(self, settings)
        self.add_input("splitter/audio", FMT)
        self.events = []
        self.frames = []
        self.received = threading.Event()


def test_handlers_never_nest_so_a_burst_comes_out_in_order(orchestrator):
    sink, sink_thread = start(SplitSink, orchestrator.url)
    poll(lambda: orchestrator.component("splitsink"), timeout_s=10)
    splitter, splitter_thread = start(Splitter, orchestrator.url)
    poll(lambda: orchestrator.component("splitter"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    clock = SampleClock(0, 16000)

    def burst(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for _ in range(500):
            c.publish("source/audio", np.zeros(320, dtype=np.int16), *clock.advance(320))

    poll(lambda: splitter.output_stats["splitter/audio"].subscribers >= 1, timeout_s=10)
    run_on(source, burst)
    poll(lambda: len(sink.events) >= 1000, timeout_s=20)
    starts = [e[2] for e in sink.events]
    assert starts == sorted(starts) and len(set(starts)) == 1000
    for component, thread in ((source, source_thread), (splitter, splitter_thread), (sink, sink_thread)):
        component.stop()
        thread.join(timeout=10)


def test_components_register_again_after_the_orchestrator_restarts(orchestrator):
    """The new orchestrator knows nothing and listens on other ZeroMQ ports: silence makes them re-register."""
    sink, sink_thread = start(Sink, orchestrator.url)
    poll(lambda: orchestrator.component("sink"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    poll(lambda: orchestrator.component("source"), timeout_s=10)
    orchestrator.kill()
    orchestrator.start()
    poll(lambda: orchestrator.component("sink") and orchestrator.component("source"), timeout_s=15)
    # and audio flows again through the peers the new orchestrator hands out
    sent = run_on(source, lambda c: (c.wait_for_subscribers("source/audio", 1, 10),
                                     c.publish("source/audio", np.zeros(160, dtype=np.int16), 0, 10_000_000,
                                               segmentation_ended=True, segment=(0, 10_000_000))))
    assert sent.wait(timeout=10)
    results = poll(lambda: orchestrator.http.get("/results", params={"component": "sink"}).json()["items"],
                   timeout_s=10)
    assert results[0]["span"] == {"start_ns": 0, "end_ns": 10_000_000}
    for component, thread in ((source, source_thread), (sink, sink_thread)):
        component.stop()
        thread.join(timeout=10)


BLAS_THREADS = """
import json
import numpy
from threadpoolctl import threadpool_info
from esiaf.runner import limit_native_threads
before = max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
limit_native_threads()
after = max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
print(json.dumps([before, after]))
"""


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: BLAS has one thread anyway")
def test_a_service_process_runs_numpy_on_one_blas_thread_unless_the_user_chose():
    """Several services share the cores: each process's BLAS runs one thread (a pool per process
    spun against the others, ten times the CPU of one voiceid embedding on a loaded machine)."""
    import json
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "MKL_NUM_THREADS")}
    run = subprocess.run([sys.executable, "-c", BLAS_THREADS], env=env, capture_output=True, text=True, timeout=60)
    before, after = json.loads(run.stdout)
    assert before > 1 and after == 1, run.stderr
    chosen = subprocess.run([sys.executable, "-c", BLAS_THREADS], env={**env, "OPENBLAS_NUM_THREADS": "2"},
                            capture_output=True, text=True, timeout=60)
    assert json.loads(chosen.stdout) == [2, 2], chosen.stderr


def test_per_stream_state_keeps_the_most_recently_heard_streams():
    from esiaf.per_stream import PerStream
    info: dict = {}
    made: list[str] = []
    states = PerStream(lambda stream_id: made.append(stream_id) or [stream_id], max_streams=2, info=info)
    assert states.get("a") == ["a"] and states.get("b") == ["b"]
    states.get("a").append(1)  # heard again: now the most recent
    states.get("c")  # b is the least recently heard: forgotten
    assert list(states) == ["a", "c"] and states["a"] == ["a", 1] and "b" not in states
    assert states.forgotten == 1 and info == {"forgotten_streams": 1}
    assert states.get("b") == ["b"] and made == ["a", "b", "c", "b"]  # afresh; a went
    assert states.pop("c") == ["c"] and states.pop("c") is None and len(states) == 1
    with pytest.raises(ValueError):
        PerStream(list, max_streams=0)

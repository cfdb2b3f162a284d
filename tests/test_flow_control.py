"""Flow control: a replay runs as fast as its slowest consumer with bounded queues and
loses nothing; live audio is still dropped and counted, never held back; SIGTERM ends a wait for a
consumer at once. Real ZeroMQ sockets, the real orchestrator, the grabber as a process."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import soundfile
import zmq

from esiaf import Audio, AudioFormat, Component, SampleClock
from esiaf.receiving import Replays
from esiaf.tools.testing import REPO, poll
from esiaf.transport import BOUNDED_TCP_BUFFER_BYTES, UNACKED_MS, Transport

FMT = AudioFormat(16000, "int16")
CHUNK = 1600  # 100 ms: a message of about 3.3 kB
QUEUE = 20  # audio_queue: messages per connection and direction
# what a hop may hold besides the queues: the kernel's buffers of one TCP connection (it doubles the
# size asked for, on both ends) and libzmq's 8 KiB batches at each end, in messages of this size
KERNEL_MESSAGES = (2 * 2 * BOUNDED_TCP_BUFFER_BYTES + 2 * 8192) // (2 * CHUNK)


class Source(Component):
    """Publishes ``chunks`` chunks as fast as it may; a replay's stream is announced not real time.
    Before each chunk it notes how far ahead of the last consumer it is (``behind()``)."""
    service = "source"

    def __init__(self, settings, chunks: int, replay: bool, behind=lambda: 0, ends: bool = False,
                 frames: int = CHUNK):
        super().__init__(settings)
        self.add_output("source/audio", FMT)
        self.chunks, self.replay, self.behind, self.ends, self.frames = chunks, replay, behind, ends, frames
        self.ahead: list[int] = []
        self.done = threading.Event()

    def produce(self):
        assert self.wait_for_subscribers("source/audio", 1, timeout_s=20)
        clock = SampleClock(1_700_000_000_000_000_000, FMT.sample_rate_hz)
        self.announce_stream(clock.origin_ns, realtime=not self.replay)
        for n in range(self.chunks):
            self.ahead.append(n - self.behind())
            self.publish("source/audio", np.full(self.frames, n % 1000, dtype=np.int16), *clock.advance(self.frames),
                         end_of_stream=n == self.chunks - 1)
            if self.stopping:
                break
        self.done.set()
        while not self.stopping and not self.ends:  # a file played to its end: run() returns
            self.sleep_until(time.monotonic() + 5)


class Relay(Component):
    """A middle hop, as the VAD is: forwards every chunk."""
    service = "relay"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_input("source/audio", FMT)
        self.add_output("relay/audio", FMT)

    def on_audio(self, audio: Audio):
        self.forward("relay/audio", audio)


class SlowSink(Component):
    """A consumer slower than its producer: ``delay_s`` per chunk; ``gate`` holds it altogether."""
    service = "sink"

    def __init__(self, settings, topic: str, delay_s: float, gate: threading.Event | None = None):
        super().__init__(settings)
        self.add_input(topic, FMT)
        self.delay_s, self.gate = delay_s, gate
        self.sequences: list[int] = []
        self.first_samples: list[int] = []
        self.ended = threading.Event()

    def on_audio(self, audio: Audio):
        if self.gate is not None:
            self.gate.wait()
        time.sleep(self.delay_s)
        if audio.frames:  # not a hop's own end-of-stream mark
            self.sequences.append(audio.sequence)
            self.first_samples.append(int(audio.samples[0, 0]))

    def on_end_of_stream(self, stream_id, audio):
        self.ended.set()


def start(component: Component) -> threading.Thread:
    thread = threading.Thread(target=component.run, daemon=True)
    thread.start()
    return thread


@pytest.fixture
def running():
    """Starts components on threads; each is stopped at the end."""
    started: list[tuple[Component, threading.Thread]] = []

    def run(component: Component) -> Component:
        started.append((component, start(component)))
        return component

    yield run
    for component, thread in reversed(started):
        component.stop()
        thread.join(timeout=10)


def settings_of(cls, url: str, **more):
    return cls.Settings(name=cls.service, orchestrator_url=url, audio_queue=QUEUE, **more)


def test_a_replay_waits_for_its_slowest_consumer_and_loses_nothing(orchestrator, running):
    chunks = 800
    sink = running(SlowSink(settings_of(SlowSink, orchestrator.url), "relay/audio", delay_s=0.003))
    relay = running(Relay(settings_of(Relay, orchestrator.url)))
    poll(lambda: relay.output_stats["relay/audio"].subscribers >= 1, timeout_s=20)
    source = running(Source(settings_of(Source, orchestrator.url), chunks, replay=True,
                            behind=lambda: len(sink.sequences)))
    assert sink.ended.wait(timeout=120), f"{len(sink.sequences)} of {chunks} chunks arrived"
    # nothing dropped at any hop, nothing lost, every chunk in order
    assert source.output_stats["source/audio"].dropped == 0 and relay.output_stats["relay/audio"].dropped == 0
    assert relay.input_stats["source/audio"].lost == 0 and sink.input_stats["relay/audio"].lost == 0
    assert sink.sequences == list(range(1, chunks + 1))
    assert sink.first_samples == [n % 1000 for n in range(chunks)]
    # the source ran at the sink's pace: never further ahead than two hops' queues and kernel buffers
    bound = 2 * (2 * QUEUE + KERNEL_MESSAGES) + 2  # + the chunk in each component's hands
    assert max(source.ahead) <= bound < chunks / 2, (max(source.ahead), bound)


def test_a_live_stream_is_dropped_and_counted_not_held_back(orchestrator, running):
    chunks, delay_s = 400, 0.02
    sink = running(SlowSink(settings_of(SlowSink, orchestrator.url), "source/audio", delay_s=delay_s))
    source = running(Source(settings_of(Source, orchestrator.url), chunks, replay=False))
    started = time.monotonic()
    assert source.done.wait(timeout=30)
    assert time.monotonic() - started < chunks * delay_s / 2  # it never waited for the sink
    dropped = source.output_stats["source/audio"].dropped
    assert dropped > 0
    poll(lambda: len(sink.sequences) + dropped == chunks or sink.ended.is_set(), timeout_s=30)
    # what was not dropped arrives, in order; a refused message takes no sequence number (no gap, no loss)
    assert sink.sequences == list(range(1, chunks - dropped + 1))
    assert sink.input_stats["source/audio"].lost == 0


def test_the_end_of_a_replay_reaches_a_consumer_slower_than_the_flush_at_shutdown(orchestrator, running):
    """A file played to its end: the producer leaves, its last queue of audio still on its way to a
    consumer held longer than FLUSH_LINGER_MS (2 s); none of it, and not the end mark, is lost."""
    chunks, gate = 2 * QUEUE, threading.Event()  # 1 s chunks: the queues hold them, the kernel's buffers few
    sink = running(SlowSink(settings_of(SlowSink, orchestrator.url), "source/audio", delay_s=0, gate=gate))
    source = Source(settings_of(Source, orchestrator.url), chunks, replay=True, ends=True, frames=16000)
    finished = threading.Event()
    threading.Thread(target=lambda: (source.run(), finished.set()), daemon=True).start()
    assert source.done.wait(timeout=30)  # all published: at most two queues and the kernel's buffers behind
    assert not finished.wait(timeout=3.0)  # its shutdown waits for the consumer, past FLUSH_LINGER_MS
    gate.set()
    assert sink.ended.wait(timeout=30) and finished.wait(timeout=10)
    assert sink.sequences == list(range(1, chunks + 1))


def test_a_consumer_busy_longer_than_the_unacknowledged_data_timeout_keeps_its_connection(orchestrator, running):
    """A consumer whose queue is full stops reading, and its TCP window closes: its producer's data goes
    unacknowledged. UNACKED_MS (4 s) would drop the connection, and every chunk sent after with it."""
    chunks, gate = 300, threading.Event()
    sink = running(SlowSink(settings_of(SlowSink, orchestrator.url), "source/audio", delay_s=0, gate=gate))
    source = running(Source(settings_of(Source, orchestrator.url), chunks, replay=True))
    poll(lambda: sink.sequences or source.output_stats["source/audio"].published > 2 * QUEUE, timeout_s=20)
    assert not source.done.wait(timeout=UNACKED_MS / 1000 + 2)  # held back all along
    gate.set()
    assert sink.ended.wait(timeout=30), f"{len(sink.sequences)} of {chunks} chunks arrived"
    assert sink.sequences == list(range(1, chunks + 1)) and source.output_stats["source/audio"].subscribers == 1


def test_sigterm_ends_a_replay_blocked_on_a_stalled_consumer_at_once(orchestrator, running, tmp_path):
    wav = tmp_path / "long.wav"
    soundfile.write(str(wav), np.zeros(60 * 16000, dtype=np.int16), 16000, subtype="PCM_16")  # 3000 chunks
    gate = threading.Event()  # never opened until the end: the consumer takes one chunk and stalls
    running(SlowSink(settings_of(SlowSink, orchestrator.url), "grabber/audio", delay_s=0, gate=gate))
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
           "ESIAF_AUDIO_QUEUE": str(QUEUE), "ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"}
    grabber = subprocess.Popen([sys.executable, "-m", "esiaf_services.grabber", "--input", str(wav), "--fast"],
                               cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        def published() -> int:
            stats = (orchestrator.component("grabber") or {}).get("stats") or {}
            return stats.get("outputs", {}).get("grabber/audio", {}).get("published", 0)

        poll(lambda: published() > QUEUE, timeout_s=30)
        time.sleep(1.0)  # a grabber not held back would play the whole file (3000 chunks) well within this
        assert grabber.poll() is None and published() < 3000 / 4, published()
        grabber.send_signal(signal.SIGTERM)
        signalled = time.monotonic()
        poll(lambda: (orchestrator.component("grabber") or {"status": "gone"})["status"] != "alive", timeout_s=3)
        assert grabber.wait(timeout=5) == 0, grabber.stderr.read() if grabber.stderr else ""
        # the unsent audio gets FLUSH_LINGER_MS (2 s) to leave, no more
        assert time.monotonic() - signalled < 4.0
    finally:
        gate.set()
        if grabber.poll() is None:
            grabber.kill()
            grabber.wait()


def test_a_replays_results_wait_for_the_orchestrator_and_stop_ends_the_wait():
    """A results socket nobody takes from: a live stream's result is refused at once, a replay's waits
    until stop() (from another thread, as a signal handler would)."""
    context = zmq.Context()
    replays = Replays()
    replays.note("replayed", replay=True)
    transport = Transport(context, inputs=[], has_outputs=False, bind_host="127.0.0.1", replays=replays)
    try:
        assert transport.send_results([b"result", b"x"], "live") is False
        stopper = threading.Timer(0.5, transport.stop)
        stopper.start()
        started = time.monotonic()
        assert transport.send_results([b"result", b"x"], "replayed") is False
        assert 0.4 <= time.monotonic() - started < 2.0  # it waited, and stop() ended the wait at once
    finally:
        transport.close()
        context.term()


def test_replays_are_bounded_and_a_stream_heard_live_is_live_again():
    replays = Replays()
    for n in range(Replays.MAX_STREAMS + 10):
        replays.note(f"s{n}", replay=True)
    assert len(replays) == Replays.MAX_STREAMS and "s0" not in replays and f"s{Replays.MAX_STREAMS + 9}" in replays
    replays.note("s20", replay=False)
    assert "s20" not in replays

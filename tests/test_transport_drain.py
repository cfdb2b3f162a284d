"""A slow consumer keeps the end of a stream whose producer has already gone."""
from __future__ import annotations

import time

import numpy as np

from esiaf import SampleClock
from esiaf.tools.testing import poll
from tests.test_component import Sink, Source, run_on, start


def test_a_slow_consumer_gets_every_chunk_after_the_producer_left(orchestrator):
    class Slow(Sink):
        def on_audio(self, audio):
            time.sleep(0.05)  # 50 ms per 20 ms chunk: falls behind
            super().on_audio(audio)

    Slow.service = "sink"
    sink, sink_thread = start(Slow, orchestrator.url)
    poll(lambda: orchestrator.component("sink"), timeout_s=10)
    source, source_thread = start(Source, orchestrator.url)
    clock = SampleClock(0, 16000)

    def send(c):
        assert c.wait_for_subscribers("source/audio", 1, timeout_s=10)
        for _ in range(60):
            c.publish("source/audio", np.zeros(320, dtype=np.int16), *clock.advance(320))

    assert run_on(source, send).wait(timeout=10)
    source.stop()  # leaves while the sink still has about 3 s of audio queued
    source_thread.join(timeout=10)
    poll(lambda: orchestrator.component("source") is None, timeout_s=10)
    poll(lambda: len(sink.events) >= 60, timeout_s=20)
    assert [e[1] for e in sink.events] == list(range(1, 61))
    sink.stop()
    sink_thread.join(timeout=10)

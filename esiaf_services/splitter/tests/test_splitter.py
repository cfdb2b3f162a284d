"""The channel splitter: mono topics per selected channel, capture times and meta carried over."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np

from esiaf import Audio, AudioFormat, Component, SampleClock, ssl_direction
from esiaf.tools.testing import REPO, poll
from esiaf_services.splitter.service import Splitter

FOUR = AudioFormat(16000, "int16", channels=4)


class Array(Component):
    """A 4-channel source: channel c of frame n holds 1000 * c + n % 1000."""
    service = "array"

    def __init__(self, settings, fmt: AudioFormat = FOUR):
        super().__init__(settings)
        self.add_output("grabber/audio", fmt)
        self.go = threading.Event()

    def produce(self):
        while not self.go.is_set() and not self.stopping:
            self.sleep_until(time.monotonic() + 0.02)
        clock = SampleClock(1_000_000_000, 16000)
        for index in range(10):
            frames = np.arange(clock.frames, clock.frames + 320) % 1000
            samples = np.stack([frames + 1000 * c for c in range(4)], axis=1).astype(np.int16)
            start_ns, end_ns = clock.advance(320)
            meta = {3: dict(ssl_directions=[ssl_direction(45.0)]),
                    5: dict(segmentation_ended=True, segment=(1_000_000_000, end_ns)),
                    9: dict(end_of_stream=True)}.get(index, {})
            self.publish("grabber/audio", samples, start_ns, end_ns, **meta)
        while not self.stopping:
            self.sleep_until(time.monotonic() + 0.05)


class Recorder(Component):
    service = "recorder"

    def __init__(self, settings, topic: str):
        super().__init__(settings)
        self.add_input(topic, AudioFormat(16000, "int16"))
        self.chunks: list[Audio] = []

    def on_audio(self, audio: Audio):
        self.chunks.append(audio)


def start(component: Component) -> Component:
    threading.Thread(target=component.run, daemon=True).start()
    return component


def test_selected_channels_become_mono_topics_with_times_and_meta(orchestrator):
    def settings(cls, name, **extra):
        return cls.Settings(name=name, orchestrator_url=orchestrator.url, **extra)

    recorders = {c: start(Recorder(settings(Recorder, f"rec{c}"), f"splitter/ch{c}")) for c in (1, 3)}
    splitter = start(Splitter(settings(Splitter, "splitter", input_channels=4, channels=[3, 1])))
    array = start(Array(settings(Array, "array")))
    poll(lambda: all(splitter.output_stats.get(f"splitter/ch{c}") and
                     splitter.output_stats[f"splitter/ch{c}"].subscribers for c in (1, 3)), timeout_s=15)
    poll(lambda: array.output_stats["grabber/audio"].subscribers, timeout_s=10)
    assert sorted(splitter.outputs) == ["splitter/ch1", "splitter/ch3"]
    array.go.set()
    for channel, recorder in recorders.items():
        poll(lambda recorder=recorder: recorder.chunks and recorder.chunks[-1].end_of_stream, timeout_s=10)
        chunks = recorder.chunks
        assert [c.sequence for c in chunks] == list(range(1, 11))
        assert [c.start_ns for c in chunks] == [1_000_000_000 + 20_000_000 * i for i in range(10)]
        assert all(c.end_ns - c.start_ns == 20_000_000 for c in chunks)
        samples = np.concatenate([c.samples[:, 0] for c in chunks])
        assert np.array_equal(samples, np.arange(3200) % 1000 + 1000 * channel)
        assert [c.ssl_directions[0].azimuth_deg for c in chunks if c.ssl_directions] == [45.0]
        ended = [c for c in chunks if c.segmentation_ended]
        assert len(ended) == 1 and ended[0].sequence == 6
        assert (ended[0].meta.segment.start_ns, ended[0].meta.segment.end_ns) == (1_000_000_000, 1_120_000_000)
        assert [c.end_of_stream for c in chunks].count(True) == 1
    for component in (array, splitter, *recorders.values()):
        component.stop()


def run_splitter(orchestrator, *args: str, **env: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
           "ESIAF_REGISTER_TIMEOUT_S": "5", **env}
    return subprocess.Popen([sys.executable, "-m", "esiaf_services.splitter", *args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_as_a_process_it_takes_the_input_format_its_producer_declares(orchestrator):
    array = start(Array(Array.Settings(name="array", orchestrator_url=orchestrator.url),
                        AudioFormat(48000, "float32", "big", 4)))
    poll(lambda: orchestrator.component("array"), timeout_s=10)
    splitter = run_splitter(orchestrator)
    try:
        splitter_info = poll(lambda: orchestrator.component("splitter"), timeout_s=30)
        mono = {"sample_rate_hz": 48000, "sample_type": "float32", "endianness": "big", "channels": 1}
        assert splitter_info["inputs"] == [{"topic": "grabber/audio", "format": {**mono, "channels": 4}}]
        assert splitter_info["outputs"] == [{"topic": f"splitter/ch{c}", "format": mono} for c in range(4)]
    finally:
        splitter.terminate()
        assert splitter.wait(timeout=10) == 0, splitter.stderr.read()
        array.stop()


def test_a_channel_the_input_lacks_is_refused_with_one_line(orchestrator):
    splitter = run_splitter(orchestrator, "--input-channels", "2", ESIAF_SPLITTER_CHANNELS="[0, 5]")
    assert splitter.wait(timeout=30) == 2
    assert "splitter: channels [5] do not exist: 'grabber/audio' has 2 (0 to 1)" in splitter.stderr.read()
    nobody = run_splitter(orchestrator, "--input-topic", "nobody/audio")
    assert nobody.wait(timeout=30) == 2
    assert "no producer of 'nobody/audio' registered" in nobody.stderr.read()

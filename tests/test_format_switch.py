"""Live: a pipeline runs, a component wanting another format joins, the topic's format switches,
and the audio a consumer gets stays continuous. And a channel mismatch ends the newcomer."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time

import numpy as np

from esiaf import Audio, AudioFormat, Component, SampleClock
from esiaf.formats import encode
from esiaf.tools.testing import REPO, poll

FMT48, FMT16 = AudioFormat(48000, "int16"), AudioFormat(16000, "int16")
TONE_HZ, CHUNK = 440.0, 960  # 20 ms at 48 kHz


def tone(start_frame: int, frames: int, rate: int) -> np.ndarray:
    return 0.5 * np.sin(2 * np.pi * TONE_HZ * np.arange(start_frame, start_frame + frames) / rate)


class Microphone(Component):
    """Plays a 440 Hz tone at 48 kHz in real time, 20 ms chunks, until told to end."""
    service = "mic"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("mic/audio", FMT48)
        self.end = threading.Event()

    def produce(self):
        if not self.wait_for_subscribers("mic/audio", 1, timeout_s=10):
            return
        clock = SampleClock(1_800_000_000_000_000_000, 48000)
        started = time.monotonic()
        while not self.stopping:
            samples = np.rint(tone(clock.frames, CHUNK, 48000) * 32767).astype(np.int16)
            start_ns, end_ns = clock.advance(CHUNK)
            self.sleep_until(started + clock.frames / 48000)
            last = self.end.is_set()
            self.publish("mic/audio", encode(samples, FMT48), start_ns, end_ns, end_of_stream=last)
            if last:
                break
        while not self.stopping:
            self.sleep_until(time.monotonic() + 0.05)


class Listener(Component):
    def __init__(self, settings, fmt: AudioFormat):
        super().__init__(settings)
        self.add_input("mic/audio", fmt)
        self.chunks: list[Audio] = []

    def on_audio(self, audio: Audio):
        self.chunks.append(audio)


def start(component: Component) -> Component:
    threading.Thread(target=component.run, daemon=True).start()
    return component


def assigned(orchestrator) -> dict:
    return next(t for t in orchestrator.http.get("/topics").json()["items"] if t["topic"] == "mic/audio")["format"]


def test_a_newcomer_switches_the_topic_and_the_consumer_hears_no_seam(orchestrator):
    def settings(cls, name):
        return cls.Settings(name=name, orchestrator_url=orchestrator.url)

    asr = start(Listener(settings(Listener, "asr"), FMT16))
    poll(lambda: orchestrator.component("asr"), timeout_s=10)
    mic = start(Microphone(settings(Microphone, "mic")))
    poll(lambda: len(asr.chunks) >= 30, timeout_s=15)  # 0.6 s of audio, sent at 16 kHz
    assert assigned(orchestrator) == FMT16.to_dict()  # a tie: the cheaper
    assert mic.context.output_links["mic/audio"].wire == FMT16  # the microphone converts
    recorder = start(Listener(settings(Listener, "recorder"), FMT48))  # wants 48 kHz: now 1 conversion, not 2
    poll(lambda: assigned(orchestrator) == FMT48.to_dict(), timeout_s=10)
    poll(lambda: len(recorder.chunks) >= 30, timeout_s=15)
    mic.end.set()
    poll(lambda: asr.chunks and asr.chunks[-1].end_of_stream, timeout_s=10)
    assert mic.context.output_links["mic/audio"].wire == FMT48  # the microphone sends what it has
    chunks = asr.chunks
    # no gap in sequence numbers (the resampler's tail travelled as a message of its own) ...
    assert [c.sequence for c in chunks] == list(range(1, len(chunks) + 1))
    assert asr.input_stats["mic/audio"].lost == 0 and asr.input_stats["mic/audio"].bad == 0
    # ... none in capture time, and the sample count matches the time covered
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(chunks))
    frames = sum(c.frames for c in chunks)
    assert abs(frames - (chunks[-1].end_ns - chunks[0].start_ns) * 16000 / 1e9) <= 1
    # and the tone goes on through the switch: every sample where it should be
    heard = np.concatenate([c.samples[:, 0] for c in chunks]) / 32768
    offset = (chunks[0].start_ns - 1_800_000_000_000_000_000) * 16000 // 10 ** 9
    error = np.abs(heard - tone(offset, len(heard), 16000))
    assert np.median(error) < 1e-3 and np.mean(error > 0.05) < 0.01
    # the late joiner got 48 kHz untouched, and it too saw no gap
    late = recorder.chunks
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(late))
    assert [c.sequence for c in late] == list(range(late[0].sequence, late[0].sequence + len(late)))
    for component in (mic, asr, recorder):
        component.stop()


def test_a_channel_mismatch_is_refused_and_the_component_exits_with_the_reason(orchestrator):
    mic = start(Microphone(Microphone.Settings(name="mic", orchestrator_url=orchestrator.url)))
    poll(lambda: orchestrator.component("mic"), timeout_s=10)
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
           "ESIAF_VAD_INPUT_TOPIC": "mic/audio", "ESIAF_VAD_CHANNELS": "2"}
    vad = subprocess.run([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=60)
    assert vad.returncode == 2
    line = vad.stderr.strip().splitlines()[-1]
    assert line.startswith("vad: orchestrator at") and "refused registration (409)" in line
    assert "'mic/audio'" in line and "16000 Hz int16 little-endian 2 ch" in line
    assert "48000 Hz int16 little-endian 1 ch" in line
    mic.stop()

"""The grabber as a process: any channel count, chunk size, capture times from sample counts, pacing."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time

import numpy as np
import soundfile

from esiaf import Audio, AudioFormat, Component
from esiaf.tools.testing import REPO, poll
from esiaf_services.grabber.service import GrabberSettings


class Recorder(Component):
    service = "recorder"

    def __init__(self, settings, fmt: AudioFormat):
        super().__init__(settings)
        self.add_input("grabber/audio", fmt)
        self.chunks: list[tuple[Audio, int]] = []  # (chunk, wall clock when received)

    def on_audio(self, audio: Audio):
        self.chunks.append((audio, time.time_ns()))


def record(orchestrator, path, fmt: AudioFormat, *args: str) -> Recorder:
    recorder = Recorder(Recorder.Settings(name="recorder", orchestrator_url=orchestrator.url), fmt)
    thread = threading.Thread(target=recorder.run, daemon=True)
    thread.start()
    poll(lambda: orchestrator.component("recorder"), timeout_s=10)
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
           "ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"}
    grabber = subprocess.run([sys.executable, "-m", "esiaf_services.grabber", "--input", str(path), *args], env=env,
                             capture_output=True, text=True, timeout=60)
    assert grabber.returncode == 0, grabber.stderr
    poll(lambda: recorder.chunks and recorder.chunks[-1][0].end_of_stream, timeout_s=10)
    recorder.stop()
    thread.join(timeout=10)
    return recorder


def test_four_channels_in_64_ms_chunks_stamped_from_sample_counts(orchestrator, tmp_path):
    samples = (np.arange(16000 * 4 * 2).reshape(-1, 4) % 30000).astype(np.int16)  # 2 s, 4 channels
    path = tmp_path / "four.wav"
    soundfile.write(str(path), samples, 16000)
    recorder = record(orchestrator, path, AudioFormat(16000, "int16", channels=4), "--fast",
                      "--set", "chunk_ms=64")
    chunks = [c for c, _ in recorder.chunks]
    assert np.array_equal(np.concatenate([c.samples for c in chunks]), samples)
    assert [c.frames for c in chunks[:-1]] == [1024] * (len(chunks) - 1)
    assert [c.sequence for c in chunks] == list(range(1, len(chunks) + 1))
    origin = chunks[0].start_ns
    frames = np.cumsum([0] + [c.frames for c in chunks])
    assert [c.start_ns for c in chunks] == [origin + f * 1_000_000_000 // 16000 for f in frames[:-1]]
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(chunks))
    assert chunks[-1].end_ns - origin == 2_000_000_000
    assert [c.end_of_stream for c in chunks].count(True) == 1


def test_real_time_pacing_publishes_each_chunk_when_its_last_sample_is_captured(orchestrator, tmp_path):
    path = tmp_path / "one-second.raw"
    path.write_bytes(np.zeros(16000, dtype="<i2").tobytes())
    recorder = record(orchestrator, path, AudioFormat(16000, "int16"))
    late_ms = [(received_ns - chunk.end_ns) / 1e6 for chunk, received_ns in recorder.chunks]
    assert len(late_ms) == round(1000 / GrabberSettings.model_fields["chunk_ms"].default)  # in its default chunks
    assert min(late_ms) >= -1.0, "a chunk was published before its audio was 'captured'"
    assert np.median(late_ms) < 5.0, late_ms


def test_a_44k1_file_reaches_a_16k_consumer_converted_and_whole(orchestrator, tmp_path):
    path = tmp_path / "cd.wav"
    seconds = 1.5
    t = np.arange(round(44100 * seconds)) / 44100
    soundfile.write(str(path), (0.5 * np.sin(2 * np.pi * 440 * t) * 32767).astype(np.int16), 44100)
    recorder = record(orchestrator, path, AudioFormat(16000, "int16"), "--fast")
    chunks = [c for c, _ in recorder.chunks]
    assert all(c.format == AudioFormat(16000, "int16") for c in chunks)
    assert sum(c.frames for c in chunks) == 16000 * seconds  # flushed at the end of the stream
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(chunks))
    assert abs(chunks[-1].end_ns - chunks[0].start_ns - seconds * 1e9) <= 1e9 / 16000
    heard = np.concatenate([c.samples[:, 0] for c in chunks]) / 32768
    expected = 0.5 * np.sin(2 * np.pi * 440 * np.arange(len(heard)) / 16000)
    assert np.median(np.abs(heard - expected)) < 1e-3

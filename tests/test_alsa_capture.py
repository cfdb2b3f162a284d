"""Live capture through ALSA: a `file` PCM that reads a FIFO fed at real-time pace stands in for a microphone."""
from __future__ import annotations

import os
import threading
import time

import pytest

from esiaf.tools.testing import shared_data
from esiaf_services.grabber.service import GrabberSettings

pytestmark = pytest.mark.e2e
RATE_HZ = 16000
# one grabber chunk (its ALSA period) of s16le mono per write: the `file` PCM standing in for the
# microphone reads its FIFO once per period and pads what is not there yet with the null PCM's silence
CHUNK_BYTES = round(RATE_HZ * GrabberSettings.model_fields["chunk_ms"].default / 1000) * 2


def feed_in_real_time(fifo, pcm: bytes, stop: threading.Event, channels: int = 1) -> None:
    """1 s of silence, the speech (s16le, interleaved), then silence until stopped; paced like a sound card."""
    chunk_bytes = CHUNK_BYTES * channels
    silence = bytes(chunk_bytes)
    with open(fifo, "wb", buffering=0) as sink:
        started = time.monotonic()
        written = 0
        stream = bytes(RATE_HZ * 2 * channels) + pcm
        while not stop.is_set():
            chunk = stream[written:written + chunk_bytes] or silence
            chunk += bytes(chunk_bytes - len(chunk))
            try:
                sink.write(chunk)
            except BrokenPipeError:
                return
            written += chunk_bytes
            time.sleep(max(0.0, started + written / (2 * channels * RATE_HZ) - time.monotonic()))


def fifo_device(tmp_path):
    """An ALSA device `esiaf_test` (in $HOME/.asoundrc) that captures from a FIFO; returns the FIFO."""
    fifo = tmp_path / "mic.fifo"
    os.mkfifo(fifo)
    (tmp_path / ".asoundrc").write_text(
        f'pcm.esiaf_test {{ type file slave.pcm "null" file "/dev/null" infile "{fifo}" format "raw" }}\n')
    return fifo


def test_live_capture_from_an_alsa_device(launch, tmp_path):
    pytest.importorskip("alsaaudio", reason="pyalsaaudio is not installed (setup.sh installs it)")
    pcm = shared_data("speech/pocketsphinx/goforward.raw").read_bytes()
    fifo = fifo_device(tmp_path)
    stop = threading.Event()
    feeder = threading.Thread(target=feed_in_real_time, args=(fifo, pcm, stop), daemon=True)
    feeder.start()
    try:
        run = launch("--mic", "esiaf_test", "--json", env={"HOME": str(tmp_path)})
        start = run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=60)
        fused = run.wait_for_line(lambda line: line.get("type") == "fused_result", timeout_s=60)
        assert fused["anchor"]["speech"]["hypotheses"][0]["text"] == "go forward ten meters"
        # capture time: the speech starts about 1.5 s into the capture (1 s of silence + its own lead-in)
        assert 1.0 < (fused["anchor"]["span"]["start_ns"] - start["start_ns"]) / 1e9 < 2.0
        assert run.stop() in (0, 130)
    finally:
        stop.set()
        feeder.join(timeout=5)


def test_live_capture_from_a_four_channel_array(launch, tmp_path):
    """The demo scene's first question, captured live as 4 channels: text and direction."""
    pytest.importorskip("alsaaudio", reason="pyalsaaudio is not installed (setup.sh installs it)")
    import json

    import soundfile

    from esiaf.tools.testing import REPO
    from esiaf_services.ssl.tracker import angle_difference_deg
    scene = REPO / "examples" / "robocup_scene.flac"
    first = json.loads(scene.with_suffix(".json").read_text())["utterances"][0]
    samples, _ = soundfile.read(str(scene), dtype="int16", frames=int((first["end_s"] + 0.5) * RATE_HZ))
    fifo = fifo_device(tmp_path)
    stop = threading.Event()
    feeder = threading.Thread(target=feed_in_real_time, args=(fifo, samples.tobytes(), stop, 4), daemon=True)
    feeder.start()
    try:
        run = launch("--mic", "esiaf_test", "--array", "respeaker4", "--grammar", "robocup", "--json",
                     env={"HOME": str(tmp_path)})
        fused = run.wait_for_line(lambda line: line.get("type") == "fused_result", timeout_s=90)
        assert fused["anchor"]["speech"]["hypotheses"][0]["text"] == "how big is the rcmp"
        assert angle_difference_deg(fused["aggregates"]["ssl"]["azimuth_deg"], first["azimuth_deg"]) <= 15
        assert run.stop() in (0, 130)
    finally:
        stop.set()
        feeder.join(timeout=5)

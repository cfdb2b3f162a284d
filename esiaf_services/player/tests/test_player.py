"""The player: what it plays is what it publishes, stamped when played; stop; ALSA; a missing device."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time
from typing import TypeVar

import numpy as np
import pytest

from esiaf import Audio, AudioFormat, Component
from esiaf.tools.testing import REPO, need_flite, poll
from esiaf_services.player.service import Player

C = TypeVar("C", bound=Component)
RATE = 16000


class Recorder(Component):
    service = "recorder"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_input("player/audio", AudioFormat(RATE, "int16"))
        self.chunks: list[Audio] = []

    def on_audio(self, audio: Audio):
        self.chunks.append(audio)


def start(component: C) -> C:
    threading.Thread(target=component.run, daemon=True).start()
    return component


def listen(orchestrator) -> Recorder:
    recorder = start(Recorder(Recorder.Settings(name="recorder", orchestrator_url=orchestrator.url)))
    poll(lambda: recorder.control is not None and recorder.control.registration is not None, timeout_s=10)
    return recorder


def published(recorder: Recorder) -> np.ndarray:
    return np.concatenate([c.samples[:, 0] for c in recorder.chunks])


def test_a_sentence_is_played_to_a_file_and_published_as_played(orchestrator, tmp_path):
    need_flite()
    recorder = listen(orchestrator)
    out = tmp_path / "loudspeaker.raw"
    player = Player(Player.Settings(name="player", orchestrator_url=orchestrator.url, output=str(out),
                                    say="Turn left at the kitchen.", exit_when_done=True, wait_for_subscribers=1))
    before_ns = time.time_ns()
    thread = threading.Thread(target=player.run)
    thread.start()
    poll(lambda: recorder.chunks and recorder.chunks[-1].end_of_stream, timeout_s=30)
    thread.join(timeout=10)
    after_ns = time.time_ns()
    played = np.frombuffer(out.read_bytes(), dtype="<i2")
    assert len(played) > RATE  # over a second of speech
    assert np.array_equal(published(recorder), played)  # exactly what went to the loudspeaker
    speech = [c for c in recorder.chunks if c.frames]
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(speech))  # one timeline
    assert speech[-1].segmentation_ended and sum(c.segmentation_ended for c in recorder.chunks) == 1
    # stamped when played: real time from the first chunk on, written at most ahead_ms before
    assert before_ns <= speech[0].start_ns and speech[-1].end_ns <= after_ns + 200_000_000
    assert speech[-1].end_ns - speech[0].start_ns == len(played) * 10**9 // RATE
    recorder.stop()


def test_stop_ends_the_item_at_once_with_an_empty_chunk_that_ends_the_utterance(orchestrator, tmp_path):
    recorder = listen(orchestrator)
    player = start(Player(Player.Settings(name="player", orchestrator_url=orchestrator.url,
                                          output=str(tmp_path / "out.wav"), wait_for_subscribers=1)))
    player.play(0.3 * np.sin(2 * np.pi * 440 * np.arange(10 * RATE) / RATE), "a long tone")
    poll(lambda: len(recorder.chunks) >= 10, timeout_s=20)
    assert player.info["playing"]["name"] == "a long tone"
    player.stop_playing()
    poll(lambda: recorder.chunks[-1].segmentation_ended, timeout_s=10)
    last = recorder.chunks[-1]
    assert last.frames == 0 and last.start_ns == recorder.chunks[-2].end_ns
    poll(lambda: player.info["playing"] is None, timeout_s=5)
    assert sum(c.frames for c in recorder.chunks) < 5 * RATE
    for component in (player, recorder):
        component.stop()


def test_a_missing_playback_device_is_one_clear_line(orchestrator):
    pytest.importorskip("alsaaudio", reason="pyalsaaudio is not installed (setup.sh installs it)")
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    done = subprocess.run([sys.executable, "-m", "esiaf_services.player", "--device", "no_such_device"], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    last = done.stderr.strip().splitlines()[-1]  # before it: libasound's own line, and the log's
    assert last.startswith("player: cannot open ALSA playback device 'no_such_device'"), done.stderr
    assert last.endswith("(list devices with: aplay -L)") and "Traceback" not in done.stderr


def test_playing_to_an_alsa_device_writes_what_is_published(orchestrator, tmp_path, monkeypatch):
    pytest.importorskip("alsaaudio", reason="pyalsaaudio is not installed (setup.sh installs it)")
    out = tmp_path / "alsa-out.raw"
    (tmp_path / ".asoundrc").write_text(
        f'pcm.esiaf_play {{ type file slave.pcm "null" file "{out}" format "raw" }}\n')
    monkeypatch.setenv("HOME", str(tmp_path))
    recorder = listen(orchestrator)
    tone = 0.3 * np.sin(2 * np.pi * 440 * np.arange(RATE // 2) / RATE)
    player = Player(Player.Settings(name="player", orchestrator_url=orchestrator.url, device="esiaf_play",
                                    exit_when_done=True, wait_for_subscribers=1))
    player.play(tone, "tone")
    thread = threading.Thread(target=player.run)
    thread.start()
    poll(lambda: recorder.chunks and recorder.chunks[-1].end_of_stream, timeout_s=30)
    thread.join(timeout=10)
    written = np.frombuffer(out.read_bytes(), dtype="<i2")
    sent = published(recorder)
    assert len(sent) == RATE // 2
    assert np.array_equal(written[:len(sent)], sent)
    recorder.stop()


def test_a_replay_s_robot_voice_is_stamped_on_its_stream_s_timeline(orchestrator, tmp_path):
    import soundfile
    recorder = listen(orchestrator)
    robot = tmp_path / "robot.wav"
    soundfile.write(str(robot), (0.3 * np.sin(2 * np.pi * 300 * np.arange(RATE) / RATE) * 32767).astype(np.int16),
                    RATE)
    player = Player(Player.Settings(name="player", orchestrator_url=orchestrator.url, output=str(tmp_path / "o.raw"),
                                    input=str(robot), follow_stream=True, fast=True, exit_when_done=True,
                                    wait_for_subscribers=1, stream_id="replay-1"))
    thread = threading.Thread(target=player.run)
    thread.start()
    start_ns = time.time_ns() - 3 * 10**9  # a grabber that started playing MICS.wav three seconds ago
    orchestrator.http.put("/streams/replay-1", json={"start_ns": start_ns, "source": "grabber",
                                                     "info": {}}).raise_for_status()
    poll(lambda: recorder.chunks and recorder.chunks[-1].end_of_stream, timeout_s=30)
    thread.join(timeout=10)
    speech = [c for c in recorder.chunks if c.frames]
    assert speech[0].start_ns == start_ns and speech[-1].end_ns == start_ns + 10**9
    assert {c.stream_id for c in recorder.chunks} == {"replay-1"}
    recorder.stop()

"""Multi-channel input: array checks at start-up, and the 4-channel pipeline end to end
(grabber → ssl + splitter → vad → asr, speech fused with ssl)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import soundfile

from esiaf.tools.testing import REPO, normalise, shared_data
from esiaf_services.ssl.tracker import angle_difference_deg
from tests.test_bad_input import assert_clear, esiaf_run

SCENE = REPO / "examples" / "robocup_scene.flac"


@pytest.fixture
def four_channels(tmp_path):
    path = tmp_path / "four.wav"
    soundfile.write(str(path), np.zeros((1600, 4), dtype="int16"), 16000)
    return path


@pytest.mark.parametrize("extra, phrases", [
    (["--array", "circular:6:0.05"], ["6 microphones but the audio has 4 channel(s)"]),
    (["--array", "pepper5"], ["unknown array 'pepper5'"]),
    (["--array", "respeaker4", "--mic-channels", "1,2,3,4"], ["channels [4] do not exist in audio of 4"]),
    (["--array", "respeaker4", "--mic-channels", "1-4"], ["--mic-channels takes channel numbers"]),
    (["--mic-channels", "0,1,2,3"], ["give --array too"]),
])
def test_the_array_must_fit_the_input(four_channels, tmp_path, extra, phrases):
    args = ["--input", str(four_channels), "--workdir", str(tmp_path), *extra]
    result = esiaf_run(*args)
    assert result.returncode == 2
    assert_clear(result, *phrases)


def test_a_grabber_with_more_channels_than_the_ssl_array_is_refused_at_start(orchestrator, four_channels):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    ssl = subprocess.Popen([sys.executable, "-m", "esiaf_services.ssl", "--array", "circular:6:0.05"],
                           cwd=REPO, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        from esiaf.tools.testing import poll
        poll(lambda: orchestrator.component("ssl"), timeout_s=30)
        grabber = subprocess.run([sys.executable, "-m", "esiaf_services.grabber",
                                  "--input", str(four_channels), "--fast"],
                                 cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    finally:
        ssl.terminate()
        ssl.wait(timeout=20)
    assert grabber.returncode == 2
    assert "grabber/audio" in grabber.stderr and "channel" in grabber.stderr, grabber.stderr
    assert "Traceback" not in grabber.stderr


@pytest.mark.e2e
def test_the_respeaker_recording_runs_through_the_whole_pipeline(launch):
    mix = shared_data("multichannel/odas2_respeaker4/mix.wav")
    run = launch("--input", str(mix), "--array", "respeaker4", "--fast", "--json")
    assert run.process.wait(timeout=180) == 0, "".join(run.stderr)
    assert run.lines[-1]["type"] == "stream_end"
    for fused in (line for line in run.lines if line.get("type") == "fused_result"):
        assert "ssl" in fused["results"]


@pytest.mark.e2e
def test_a_six_channel_recording_with_the_microphones_on_channels_1_to_4(launch, tmp_path):
    """The ReSpeaker's 6-channel firmware layout: processed audio on 0 (here: mic 0), mics on 1-4, playback on 5."""
    truth = json.loads(SCENE.with_suffix(".json").read_text())["utterances"][:2]
    mics, rate = soundfile.read(str(SCENE), dtype="int16", frames=int((truth[-1]["end_s"] + 1.0) * 16000))
    six = tmp_path / "six.wav"
    soundfile.write(str(six), np.concatenate([mics[:, :1], mics, np.zeros_like(mics[:, :1])], axis=1), rate)
    run = launch("--input", str(six), "--array", "respeaker4", "--mic-channels", "1,2,3,4", "--grammar", "robocup",
                 "--fast", "--json")
    assert run.process.wait(timeout=180) == 0, "".join(run.stderr)
    fused = [line for line in run.lines if line.get("type") == "fused_result"]
    assert [normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused] == \
        [normalise(t["text"]) for t in truth]
    for f, t in zip(fused, truth, strict=True):
        assert angle_difference_deg(f["aggregates"]["ssl"]["azimuth_deg"], t["azimuth_deg"]) <= 15


@pytest.mark.e2e
def test_each_question_of_the_demo_scene_comes_with_its_text_direction_emotion_and_gender(launch):
    """The README's demo command (played fast): one fused answer per question, every analyser in it."""
    truth = json.loads(SCENE.with_suffix(".json").read_text())["utterances"]
    run = launch("--input", str(SCENE), "--array", "respeaker4", "--grammar", "robocup", "--fast", "--json")
    assert run.process.wait(timeout=180) == 0, "".join(run.stderr)
    start_ns = next(line for line in run.lines if line.get("type") == "stream_start")["start_ns"]
    fused = [line for line in run.lines if line.get("type") == "fused_result"]
    assert len(fused) == len(truth), fused
    for f, t in zip(fused, truth, strict=True):
        assert normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) == normalise(t["text"])
        assert abs((f["anchor"]["span"]["start_ns"] - start_ns) / 1e9 - t["start_s"]) < 0.3, (f["anchor"], t)
        azimuth = f["aggregates"]["ssl"]["azimuth_deg"]
        assert angle_difference_deg(azimuth, t["azimuth_deg"]) <= 15, (azimuth, t)
        assert f["completion"] == "complete", f  # nobody timed out: every analyser answered
        for kind, labels in (("emotion", {"neutral", "angry", "happy", "sad"}), ("gender", {"female", "male"})):
            label = f["aggregates"][kind]
            assert label["label"] in labels and 0 < label["probability"] <= 1, (kind, label)
            assert set(label["distribution"]) == labels and abs(sum(label["distribution"].values()) - 1) < 1e-3
            assert len(f["results"][kind]) == 1 and f["results"][kind][0]["span"] == f["anchor"]["span"]


def test_list_settings_can_be_given_with_set():
    from esiaf.runner import parse_set
    assert parse_set(["mic_channels=[1, 2, 3, 4]", "channels=6", "array=respeaker4"]) == \
        {"mic_channels": [1, 2, 3, 4], "channels": 6, "array": "respeaker4"}

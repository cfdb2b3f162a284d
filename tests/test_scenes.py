"""The labelled-scene tool: rendering, its truth, its command line and its errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import soundfile

from esiaf.scenes import NoiseSource, Scene, SceneError, SpeechSource, render
from esiaf.tools.testing import REPO, need_flite, shared_data

CLIP = "speech/cmu_arctic/cmu_arctic_us_aew_a0001.wav"


def lag_samples(a: np.ndarray, b: np.ndarray, max_lag: int = 8) -> int:
    """How many samples b lags behind a (GCC-PHAT)."""
    n = 2 * len(a)
    cross = np.fft.rfft(b, n) * np.conj(np.fft.rfft(a, n))
    corr = np.fft.irfft(cross / (np.abs(cross) + 1e-12), n)
    lags = np.r_[corr[:max_lag + 1], corr[-max_lag:]]
    return int(np.r_[np.arange(max_lag + 1), np.arange(-max_lag, 0)][np.argmax(lags)])


@pytest.mark.parametrize("azimuth, first, last", [(0.0, 2, 0), (90.0, 3, 1), (180.0, 0, 2), (270.0, 1, 3)])
def test_a_source_reaches_the_nearest_microphone_first_and_the_truth_says_where_it_speaks(azimuth, first, last):
    clip = shared_data(CLIP)
    scene = Scene(array="respeaker4", rt60_s=0.2, speech=[SpeechSource(clip=str(clip), azimuth_deg=azimuth,
                                                                       onset_s=0.7, text="hello")])
    signals, truth = render(scene)
    assert signals.shape[1] == 4 and np.max(np.abs(signals)) == pytest.approx(10 ** (-3 / 20))
    u, = truth["utterances"]
    assert (u["text"], u["azimuth_deg"], u["distance_m"]) == ("hello", azimuth, 1.5)
    speech = np.flatnonzero(np.abs(signals[:, 0]) > 0.02 * np.max(np.abs(signals[:, 0])))
    assert abs(speech[0] / 16000 - u["start_s"]) < 0.02 and abs(speech[-1] / 16000 - u["end_s"]) < 0.3
    # ReSpeaker mics 0..3 sit at -x, -y, +x, +y: the far-side mic hears the source about 3 samples later
    part = signals[int(u["start_s"] * 16000):int(u["end_s"] * 16000)]
    assert lag_samples(part[:, first], part[:, last]) >= 2


def test_noise_is_mixed_at_the_asked_snr():
    from esiaf.scenes import render_parts
    clip, noise = shared_data(CLIP), shared_data("noise/speech_commands_bg/exercise_bike.wav")
    scene = Scene(array="pepper4", speech=[SpeechSource(clip=str(clip), azimuth_deg=45, onset_s=0.2)],
                  noise=[NoiseSource(clip=str(noise), azimuth_deg=200, snr_db=10)])
    speech, noise_part, truth = render_parts(scene)
    u, = truth["utterances"]
    active = slice(int(u["start_s"] * 16000), int(u["end_s"] * 16000))
    ratio_db = 10 * np.log10(np.mean(speech[active, 0] ** 2) / np.mean(noise_part[:, 0] ** 2))
    assert ratio_db == pytest.approx(10, abs=0.5)
    assert truth["noise"] == [{"clip": "exercise_bike.wav", "azimuth_deg": 200, "snr_db": 10, "distance_m": 2.0}]


def test_command_line_renders_a_yaml_scene_with_flite_speech(tmp_path):
    need_flite()
    (tmp_path / "scene.yaml").write_text(
        "array: circular:6:0.05\nrt60_s: 0.3\n"
        "speech:\n  - {say: 'what is a chatbot', voice: slt, azimuth_deg: 135, onset_s: 0.5}\n")
    out = tmp_path / "out" / "scene.flac"
    result = subprocess.run([sys.executable, "-m", "esiaf.scenes", str(tmp_path / "scene.yaml"), "--out", str(out)],
                            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    info = soundfile.info(str(out))
    assert (info.channels, info.samplerate, info.subtype) == (6, 16000, "PCM_16")
    truth = json.loads(out.with_suffix(".json").read_text())
    assert truth["audio"] == "scene.flac" and truth["array"] == "circular:6:0.05"
    u, = truth["utterances"]
    assert (u["text"], u["speaker"], u["azimuth_deg"]) == ("what is a chatbot", "slt", 135)
    assert 0.5 < u["start_s"] < u["end_s"] < info.duration


@pytest.mark.parametrize("yaml_text, message", [
    ("speech: [{say: hi, azimuth_deg: 0, distance_m: 4}]", "outside the room"),
    ("speeches: []", "unknown scene keys speeches"),
    ("speech: [{azimuth_deg: 0}]", "give exactly one of clip or say"),
    ("speech: [{clip: missing.wav, azimuth_deg: 0}]", "cannot read clip"),
    ("array: pepper5\nspeech: [{say: hi, azimuth_deg: 0}]", "unknown array 'pepper5'"),
    ("speech: [{say: hi, azimuth: 0}]", "bad source in scene"),
])
def test_bad_scenes_are_refused_with_one_clear_line(tmp_path, yaml_text, message):
    (tmp_path / "bad.yaml").write_text(yaml_text + "\n")
    result = subprocess.run([sys.executable, "-m", "esiaf.scenes", str(tmp_path / "bad.yaml"), "--out",
                             str(tmp_path / "x.wav")], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_an_impossible_rt60_is_a_scene_error():
    with pytest.raises(SceneError, match=r"RT60 0\.01 s is impossible"):
        render(Scene(rt60_s=0.01, speech=[SpeechSource(clip="unused.wav", azimuth_deg=0)]))

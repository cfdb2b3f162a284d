"""Accuracy on simulated rooms: a speaker 1.5 m from the array, RT60 0.4 s, a noise source 10 dB below.

One scene per array: six CMU ARCTIC utterances, one after another, from 0°, 90°, 180°, 270° and two
angles that are not multiples of 45° (30°, 200°), a kitchen noise source at 120°, 2 m away. The
ssl component (real framing, background tracking and localiser, its sends captured) runs over the
scene; its best direction per 128 ms frame is scored against the truth, on the frames that lie
within an utterance's speech.
"""
from __future__ import annotations

import pytest
import soundfile

from esiaf.scenes import NoiseSource, Scene, SpeechSource, render
from esiaf.testing import shared_data
from services.ssl.offline import localise, score

ANGLES = (0.0, 90.0, 180.0, 270.0, 30.0, 200.0)
CLIPS = ("arctic_a0010", "cmu_arctic_us_aew_a0001", "cmu_arctic_us_aew_a0002", "cmu_arctic_us_aew_a0003",
         "cmu_arctic_us_axb_a0004", "cmu_arctic_us_axb_a0005")


def scene_for(array: str) -> Scene:
    speech, onset = [], 0.5
    for angle, name in zip(ANGLES, CLIPS):
        clip = shared_data(f"speech/cmu_arctic/{name}.wav")
        speech.append(SpeechSource(clip=str(clip), azimuth_deg=angle, distance_m=1.5, onset_s=onset,
                                   speaker=name.split("_")[-2] if "us" in name else "a0010"))
        onset += soundfile.info(str(clip)).duration + 0.3
    noise = shared_data("noise/speech_commands_bg/doing_the_dishes.wav")
    return Scene(array=array, rt60_s=0.4, speech=speech,
                 noise=[NoiseSource(clip=str(noise), azimuth_deg=120.0, distance_m=2.0, snr_db=10.0)])


@pytest.mark.parametrize("array", ["pepper4", "respeaker4"])
def test_azimuth_error_on_a_reverberant_noisy_scene(array):
    signals, truth = render(scene_for(array))
    assert [u["azimuth_deg"] for u in truth["utterances"]] == list(ANGLES)
    result = score(localise(signals, truth["sample_rate_hz"], array=array), truth["utterances"])

    assert result["speech_frames"] >= 100
    assert result["located_share"] >= 0.85, result  # speech frames that got a direction, not "nothing"
    assert result["median_error_deg"] <= 5, result
    assert result["within_15"] >= 0.90, result
    for angle in result["utterances"]:  # every angle on its own (9-27 frames each)
        assert angle["median_error_deg"] <= 5, angle
        assert angle["within_15"] >= 0.80, angle

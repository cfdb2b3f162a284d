"""Accuracy on simulated rooms: a speaker 1.5 m from the array, RT60 0.4 s, a noise source 10 dB below.

One scene per array (esiaf_services.ssl.offline.accuracy_scene): six CMU ARCTIC utterances, one after
another, from 0°, 90°, 180°, 270° and two angles that are not multiples of 45° (30°, 200°), kitchen
noise from 120°, 2 m away. The ssl component (real framing, background tracking and localiser, its
sends captured) runs over the scene; its best direction per 128 ms frame is scored against the
truth on the frames that lie within an utterance's speech.
"""
from __future__ import annotations

import pytest

from esiaf.scenes import render
from esiaf.tools.testing import SHARED_DATA, shared_data
from esiaf_services.ssl.offline import ANGLES, CLIPS, NOISE_CLIP, accuracy_scene, localise, score


@pytest.mark.parametrize("array", ["pepper4", "respeaker4"])
def test_azimuth_error_on_a_reverberant_noisy_scene(array):
    for name in CLIPS:
        shared_data(f"speech/cmu_arctic/{name}.wav")
    shared_data(NOISE_CLIP)
    signals, truth = render(accuracy_scene(array, SHARED_DATA))
    assert [u["azimuth_deg"] for u in truth["utterances"]] == list(ANGLES)
    result = score(localise(signals, truth["sample_rate_hz"], array=array), truth["utterances"])

    assert result["speech_frames"] >= 100
    assert result["located_share"] >= 0.85, result  # speech frames that got a direction, not "nothing"
    assert result["median_error_deg"] <= 5, result
    assert result["within_15"] >= 0.90, result
    for angle in result["utterances"]:  # every angle on its own (9-27 frames each)
        assert angle["median_error_deg"] <= 5, angle
        assert angle["within_15"] >= 0.80, angle

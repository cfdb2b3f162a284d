"""The robot's own direction learnt from the player's reference, on a rendered room: the robot's
loudspeaker 10 cm from the array (in its head, below it) saying flite sentences, 10 dB louder at the
microphones than a person 1.5 m away who talks both while it speaks and while it is silent. A real
Ssl component (its framing, tracker and localiser; sends captured) hears the microphones and, on
``player/audio``, what the loudspeaker played."""
from __future__ import annotations

import numpy as np
import pytest

from esiaf.scenes import Scene, SceneError, SpeechSource, render, speak
from esiaf.tools.testing import shared_data
from esiaf_services.ssl.offline import localise
from esiaf_services.ssl.self_direction import SelfDirection
from esiaf_services.ssl.tracker import angle_difference_deg

RATE = 16000
ROBOT_DEG, PERSON_DEG = 120.0, 250.0
ROBOT_SPANS_S = ((0.5, 5.5), (8.0, 12.5))  # where the robot's sentences are placed (each filled from its start)


def robot_scene(tmp_path):
    import soundfile
    try:
        sentence = speak("The kitchen is on your left, next to the big window. Do you have another question?",
                         "kal16", RATE)
    except SceneError as exc:
        pytest.skip(f"needs flite: {exc}")
    track = np.zeros(int(15.0 * RATE))
    for start, end in ROBOT_SPANS_S:
        part = np.tile(sentence, 3)[:int((end - start) * RATE)]
        track[int(start * RATE):int(start * RATE) + len(part)] = part
    robot = tmp_path / "robot.wav"
    soundfile.write(str(robot), track.astype(np.float32), RATE)
    clips = [shared_data(f"speech/cmu_arctic/cmu_arctic_us_aew_a000{n}.wav") for n in (1, 2, 3)]
    delay_s = 0.08  # the loudspeaker's echo after what the player published
    speech = [SpeechSource(clip=str(robot), azimuth_deg=ROBOT_DEG, distance_m=0.1, elevation_deg=-30.0,
                           onset_s=delay_s, gain_db=10.0, speaker="robot"),
              # the person: once while the robot speaks, twice while it is silent
              SpeechSource(clip=str(clips[0]), azimuth_deg=PERSON_DEG, onset_s=3.0, speaker="person"),
              SpeechSource(clip=str(clips[1]), azimuth_deg=PERSON_DEG, onset_s=5.8, speaker="person"),
              SpeechSource(clip=str(clips[2]), azimuth_deg=PERSON_DEG, onset_s=12.8, speaker="person")]
    signals, truth = render(Scene(array="respeaker4", rt60_s=0.35, speech=speech, tail_s=0.5, seed=3))
    return signals, track[:len(signals)], truth


def test_the_robots_direction_is_learnt_from_its_reference_and_marks_it_self(tmp_path):
    signals, reference, truth = robot_scene(tmp_path)
    person = [u for u in truth["utterances"] if u["speaker"] == "person"]
    component: list = []
    frames = localise(signals, RATE, array="respeaker4", reference=reference, component=component)
    learnt = component[0].streams.get("offline").self_direction
    assert learnt.azimuth_deg is not None, (learnt.playing_frames, learnt.quiet_frames)
    assert angle_difference_deg(learnt.azimuth_deg, ROBOT_DEG) <= 15, learnt.azimuth_deg

    # the robot alone after the direction is learnt (its second stretch, before the person talks over it)
    robot_alone = [f for f in frames if f.start_s >= 8.3 and f.end_s <= 12.5 and f.azimuth_deg is not None]
    assert len(robot_alone) >= 20
    assert np.mean([f.source_id == "self" for f in robot_alone]) >= 0.8, [f.source_id for f in robot_alone]
    # the person alone: never the robot
    alone = [f for u in person[1:] for f in frames if u["start_s"] <= f.start_s and f.end_s <= u["end_s"]
             and f.azimuth_deg is not None and not 8.0 <= f.start_s <= 12.6]
    assert len(alone) >= 10
    assert not [f for f in alone if f.source_id == "self"]
    assert np.mean([angle_difference_deg(f.azimuth_deg, PERSON_DEG) <= 15 for f in alone]) >= 0.8


def test_without_a_reference_the_setting_decides(tmp_path):
    signals, _, _ = robot_scene(tmp_path)
    unmarked = localise(signals, RATE, array="respeaker4")
    assert not [f for f in unmarked if f.source_id == "self"]
    marked = localise(signals, RATE, array="respeaker4", self_azimuth_deg=ROBOT_DEG)
    assert [f for f in marked if f.source_id == "self" and 8.3 <= f.start_s <= 12.0]


def test_frames_wait_for_their_reference_and_the_robot_starting_or_stopping_counts_for_neither():
    learner = SelfDirection(width_deg=40.0, max_delay_ms=300.0, min_frames=3)
    ns = 1_000_000_000
    loud, quiet = np.full(1600, 0.1), np.zeros(1600)
    for k in range(5):  # frames at 1.0-1.5 s from 90°, the reference not there yet
        learner.frame(ns + k * ns // 10, ns + (k + 1) * ns // 10, [90.0])
    assert learner.playing_frames == 0 and learner.azimuth_deg is None
    for k in range(20):  # the loudspeaker played 0-2 s: the frames are counted now
        learner.reference(k * ns // 10, (k + 1) * ns // 10, loud)
    assert learner.playing_frames == 5 and angle_difference_deg(learner.azimuth_deg, 90.0) <= 2
    for k in range(20, 40):  # quiet from 2 s
        learner.reference(k * ns // 10, (k + 1) * ns // 10, quiet)
    learner.frame(2 * ns + ns // 4, 2 * ns + 7 * ns // 20, [200.0])  # its echo's reach ends 50 ms of speech: neither
    learner.frame(3 * ns, 3 * ns + ns // 10, [200.0])  # quiet
    assert (learner.playing_frames, learner.quiet_frames) == (5, 1)

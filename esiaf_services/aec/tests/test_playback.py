"""esiaf run --input MICS.wav --playback ROBOT.wav: the robot talks over a person's questions; the
player plays its voice on the input's timeline and the echo canceller takes it out."""
from __future__ import annotations

import json

import numpy as np
import pytest
import soundfile

from esiaf.tools.testing import REPO, need_flite, normalise
from esiaf_services.aec.tests.test_aec import echo_path, to_pcm
from esiaf_services.player.tts import say

pytestmark = pytest.mark.e2e
RATE = 16000
ROBOT_SAYS = ("I am sorry, I did not catch that. Could you please say it again a little louder?",
              "The kitchen is on the left, next to the dining room, behind the blue door.",
              "My battery is almost full, so I can keep going for another two hours.")


def robot_over_questions(tmp_path, echo_above_person_db: float):
    """MICS.wav: the example's five questions (a person) with the robot's voice over most of them,
    echoed 120 ms late from a clock 100 ppm fast; ROBOT.wav: what the robot said; the questions."""
    person, rate = soundfile.read(str(REPO / "examples/robocup_questions.wav"))
    assert rate == RATE
    truth = json.loads((REPO / "examples/robocup_questions.json").read_text())["sentences"]
    robot = np.zeros(len(person))
    at = int(0.5 * RATE)
    for sentence in ROBOT_SAYS * 2:
        voice = say(sentence, "kal16", RATE)[:len(robot) - at]
        robot[at:at + len(voice)] = voice
        at += len(voice) + int(0.4 * RATE)
        if at >= len(robot):
            break
    echo = echo_path(0.5 * robot, 1, delay_ms=120, ppm=100)[:, 0]
    speaking = np.abs(person) > 0.02 * np.max(np.abs(person))
    gain = np.sqrt(np.mean(echo[echo != 0] ** 2) / np.mean(person[speaking] ** 2)) * 10 ** (-echo_above_person_db / 20)
    mics = person * gain + echo
    mics *= 0.5 / np.max(np.abs(mics))
    soundfile.write(str(tmp_path / "mics.wav"), to_pcm(mics), RATE)
    soundfile.write(str(tmp_path / "robot.wav"), to_pcm(0.5 * robot), RATE)
    return tmp_path / "mics.wav", tmp_path / "robot.wav", truth


def questions_heard(launch, truth, *args: str):
    run = launch(*args, "--grammar", "robocup", "--fast", "--json", "--without", "emotion,gender,voiceid")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=300)
    fused = [line for line in run.lines if line.get("type") == "fused_result" and line["revision"] == 1]
    heard = {normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused
             if f["anchor"].get("speech") and f["anchor"]["speech"]["hypotheses"]}
    return [s["text"] for s in truth if normalise(s["text"]) in heard], run


def test_the_robot_talking_over_the_questions_is_cancelled_and_more_questions_are_heard(launch, tmp_path):
    need_flite()
    mics, robot, truth = robot_over_questions(tmp_path, echo_above_person_db=6.0)
    without, _ = questions_heard(launch, truth, "--input", str(mics))
    heard, run = questions_heard(launch, truth, "--input", str(mics), "--playback", str(robot))
    # the recogniser is not what is tested: what the canceller gives it is
    assert len(heard) >= 2 and len(heard) > len(without), (heard, without, run.describe())
    played, _ = soundfile.read(str(run.workdir / "loudspeaker.wav"), dtype="int16")
    expected, _ = soundfile.read(str(robot), dtype="int16")
    assert np.array_equal(played, expected)  # the whole robot voice went to the loudspeaker, as it was

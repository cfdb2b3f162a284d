"""The robot's voice through the orchestrator (real orchestrator process, real ZeroMQ sockets, real HTTP and
websocket clients, the real Silero vad): say, play and stop through the API, each item reported as a
playback result; the robot's own voice heard back tagged and left out of /fused and the websocket; a person
who starts speaking while the robot plays is a barge_in event, and under ``stop`` the player stops."""
from __future__ import annotations

import io
import json
import threading
import time
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
import soundfile
from websockets.sync.client import connect

from esiaf import Component
from esiaf.tools.testing import Orchestrator, need_flite, poll
from esiaf_services.grabber.service import Grabber, GrabberSettings
from esiaf_services.player.service import Player
from esiaf_services.player.tts import say
from esiaf_services.vad.service import Vad, VadSettings

C = TypeVar("C", bound=Component)
RATE = 16000
UTTERANCES = {"fusions": [{"name": "utterances", "anchor": "vad"}]}  # no recogniser: the vad's segments


def start(component: C) -> C:
    threading.Thread(target=component.run, daemon=True).start()
    return component


def wav(samples: np.ndarray, rate: int = RATE, subtype: str = "PCM_16") -> bytes:
    buffer = io.BytesIO()
    soundfile.write(buffer, samples, rate, format="WAV", subtype=subtype)
    return buffer.getvalue()


def tone(seconds: float, level: float = 0.1) -> np.ndarray:
    return level * np.sin(2 * np.pi * 330 * np.arange(round(seconds * RATE)) / RATE)


def player(orchestrator: Orchestrator, out: Path, stream: str, **settings) -> Player:
    playing = start(Player(Player.Settings(name="player", orchestrator_url=orchestrator.url, output=str(out),
                                           stream_id=stream, **settings)))
    poll(lambda: orchestrator.http.get(f"/streams/{stream}/playing").status_code == 200, timeout_s=20)
    return playing


def playbacks(orchestrator: Orchestrator, stream: str) -> list[dict]:
    items = orchestrator.http.get("/results", params={"type": "playback", "stream": stream}).json()["items"]
    return sorted(items, key=lambda r: r["id"])


def test_play_and_stop_through_the_api_are_reported_as_playback_results(orchestrator, tmp_path):
    assert orchestrator.http.get("/streams/robot/playing").status_code == 404  # no player yet
    robot = player(orchestrator, tmp_path / "loudspeaker.raw", "robot")
    assert orchestrator.http.get("/streams/robot/playing").json()["playing"] is None
    answer = orchestrator.http.post("/streams/robot/play", params={"name": "a long tone"},
                                    content=wav(tone(10.0), rate=48000))  # resampled to the player's 16 kHz
    assert answer.status_code == 202, answer.text
    assert answer.json()["seconds"] == pytest.approx(10.0 / 3, abs=0.01)
    now = poll(lambda: orchestrator.http.get("/streams/robot/playing").json()["playing"], timeout_s=20)
    assert now["name"] == "a long tone" and now["end_ns"] - now["start_ns"] == pytest.approx(10 / 3 * 1e9, abs=1e6)
    first, = poll(lambda: playbacks(orchestrator, "robot"), timeout_s=10)
    assert first["playback"]["text"] == "a long tone" and first["playback"]["attributes"]["stopped"] is False
    assert (first["span"]["start_ns"], first["span"]["end_ns"]) == (now["start_ns"], now["end_ns"])
    assert orchestrator.http.delete("/streams/robot/playing").status_code == 202
    poll(lambda: orchestrator.http.get("/streams/robot/playing").json()["playing"] is None, timeout_s=10)
    _, revised = poll(lambda: len(playbacks(orchestrator, "robot")) == 2 and playbacks(orchestrator, "robot"),
                      timeout_s=10)
    assert revised["playback"]["attributes"] == {"item": 1, "part": 0, "stopped": True}
    assert first["span"]["start_ns"] == revised["span"]["start_ns"] < revised["span"]["end_ns"] < now["end_ns"]
    assert robot.played == 1
    robot.stop()


def test_say_goes_to_the_streams_player_only(orchestrator, tmp_path):
    need_flite()
    robot = player(orchestrator, tmp_path / "loudspeaker.raw", "robot")
    assert orchestrator.http.post("/streams/other/say", json={"text": "Hello."}).status_code == 404
    answer = orchestrator.http.post("/streams/robot/say", json={"text": "Hello there.", "voice": "kal"})
    assert answer.status_code == 202, answer.text
    said = poll(lambda: playbacks(orchestrator, "robot"), timeout_s=20)
    assert said[0]["playback"]["text"] == "say: Hello there."
    robot.stop()


class Scene:
    """A microphone file (what the echo canceller left: the robot's residual echo and a person) and what the
    robot plays on the same timeline (its player follows the stream's start)."""

    def __init__(self, folder: Path, robot_echo: bool):
        self.folder = folder
        lead = np.zeros(RATE)
        self.robot = say("The kitchen is to your left, next to the big window.", "kal16", RATE) * 0.5
        person = say("Where is the bathroom?", "slt", RATE) * 0.5
        if robot_echo:  # the robot speaks, its echo is heard; the person asks in the silence after it
            played = np.concatenate([lead, self.robot])
            mics = np.concatenate([lead, self.robot, np.zeros(RATE * 3 // 2), person, np.zeros(RATE * 2)])
            self.person_onset_s = 1.0 + len(self.robot) / RATE + 1.5
        else:  # the robot plays a long sound (cancelled entirely); the person talks over it
            played = tone(12.0, 0.05)
            mics = np.concatenate([lead, person, np.zeros(RATE * 2)])
            self.person_onset_s = 1.0
        self.played, self.mics = folder / "robot.wav", folder / "mics.wav"
        soundfile.write(str(self.played), played, RATE, subtype="PCM_16")
        soundfile.write(str(self.mics), mics, RATE, subtype="PCM_16")
        self.seconds = len(mics) / RATE


def run_scene(orchestrator: Orchestrator, scene: Scene, stream: str,
              **vad_settings) -> tuple[Player, list[tuple[float, dict]]]:
    """Starts the player (following the stream), the vad and the grabber (real time); the websocket's messages
    with their arrival times until the stream ends."""
    robot = player(orchestrator, scene.folder / "loudspeaker.raw", stream, input=str(scene.played),
                   follow_stream=True)
    vad = start(Vad(VadSettings(name="vad", orchestrator_url=orchestrator.url, **vad_settings)))
    poll(lambda: vad.control is not None and vad.control.registration is not None, timeout_s=30)
    received: list[tuple[float, dict]] = []
    with connect(f"{orchestrator.ws_url}/ws/fused?stream={stream}") as ws:
        start(Grabber(GrabberSettings(name="grabber", orchestrator_url=orchestrator.url, input=str(scene.mics),
                                      stream_id=stream, wait_for_subscribers=1)))
        deadline = time.monotonic() + scene.seconds + 30
        while time.monotonic() < deadline:
            message = json.loads(ws.recv(timeout=deadline - time.monotonic()))
            received.append((time.time_ns(), message))
            if message["type"] == "stream_end":
                break
    vad.stop()
    return robot, received


@pytest.mark.e2e
def test_the_robots_own_voice_is_left_out_and_the_persons_question_is_fused(tmp_path):
    need_flite()
    orchestrator = Orchestrator(tmp_path, config={**UTTERANCES, "barge_in_policy": "ignore"})
    try:
        scene = Scene(tmp_path, robot_echo=True)
        robot, received = run_scene(orchestrator, scene, "s1")
        shown = [m for _, m in received if m["type"] == "fused_result"]
        assert [m["source"] for m in shown] == ["person"]  # the robot's echo never reached the client
        assert shown[0]["playback_overlap"] < 0.5
        every = orchestrator.http.get("/fused", params={"stream": "s1", "include_robot": "true"}).json()["items"]
        robots = [f for f in every if f["source"] == "robot"]
        assert len(robots) == 1 and robots[0]["playback_overlap"] >= 0.5
        assert [f["id"] for f in orchestrator.http.get("/fused", params={"stream": "s1"}).json()["items"]] == \
            [shown[0]["id"]]
        robot.stop()
    finally:
        orchestrator.close()


@pytest.mark.e2e
def test_a_person_speaking_over_the_robot_is_a_barge_in_and_stops_it(tmp_path):
    orchestrator = Orchestrator(tmp_path, config={**UTTERANCES, "barge_in_policy": "stop"})
    try:
        need_flite()
        scene = Scene(tmp_path, robot_echo=False)
        robot, received = run_scene(orchestrator, scene, "s2")
        start_ns = orchestrator.http.get("/streams/s2").json()["start_ns"]
        barge_ins = [(at, m) for at, m in received if m["type"] == "barge_in"]
        assert len(barge_ins) == 1
        _at_ns, event = barge_ins[0]
        onset_ns = start_ns + round(scene.person_onset_s * 1e9)
        assert abs(event["capture_ns"] - onset_ns) < 300_000_000 and event["policy"] == "stop"
        stopped = [r for r in playbacks(orchestrator, "s2") if r["playback"]["attributes"]["stopped"]]
        assert len(stopped) == 1 and stopped[0]["span"]["end_ns"] < start_ns + 5 * 10**9  # not 12 s of tone
        assert orchestrator.http.get("/streams/s2/playing").json()["playing"] is None
        person = [m for _, m in received if m["type"] == "fused_result"]
        assert [m["source"] for m in person] == ["person"]
        robot.stop()
    finally:
        orchestrator.close()


class BabbleScene(Scene):
    """The robot plays a long tone (cancelled entirely) while four flite voices babble in a reverberant room
    from the start (a stretch of speech the vad opens and announces at once), and a person asks over the
    babble from 4 s, 15 dB above it."""

    def __init__(self, folder: Path):
        from scipy.signal import fftconvolve

        from bench.barge_in import onset
        from esiaf.tools.evaluation import babble_clip
        self.folder = folder
        answers = ["The kitchen is to your left, next to the big window.", "I can bring you a drink from the fridge.",
                   "The capital of Germany is Berlin.", "There are five people in this room."]
        babble = soundfile.read(str(babble_clip(np.random.default_rng(1), answers, folder / "babble.wav", 8.0)))[0]
        rng = np.random.default_rng(0)
        t = np.arange(round(0.6 * RATE)) / RATE
        rir = rng.normal(0, 1, len(t)) * np.exp(-6.9 * t / 0.6)  # a room's tail, RT60 0.6 s
        rir[0] = 3
        babble = fftconvolve(babble, rir)[:len(babble)]
        babble /= np.abs(babble).max()
        babble += rng.normal(0, 1, len(babble)) * np.sqrt(np.mean(babble ** 2)) / np.sqrt(10)
        person = say("Where is the bathroom?", "slt", RATE)
        loud = person[np.abs(person) > 0.02 * np.abs(person).max()]
        person *= np.sqrt(np.mean(babble ** 2) / np.mean(loud ** 2)) * 10 ** (15 / 20)
        mics = babble.copy()
        mics[4 * RATE:4 * RATE + len(person)] += person[:len(mics) - 4 * RATE]
        mics *= 0.3 / np.abs(mics).max()
        self.person_onset_s = 4.0 + onset(person) / RATE
        self.played, self.mics = folder / "robot.wav", folder / "mics.wav"
        soundfile.write(str(self.played), tone(12.0, 0.05), RATE, subtype="PCM_16")
        soundfile.write(str(self.mics), mics, RATE, subtype="PCM_16")
        self.seconds = len(mics) / RATE


@pytest.mark.e2e
def test_a_person_starting_over_babble_the_vad_already_announced_is_a_barge_in(tmp_path):
    """The babble opens the vad's stretch of speech (its barge-in at the start); the person starting 4 s in
    gets a barge-in of their own, from the sharp rise of the speech probability (silero.rise_to), not
    none (one speech_start per stretch, before)."""
    need_flite()
    orchestrator = Orchestrator(tmp_path, config={**UTTERANCES, "barge_in_policy": "ignore"})
    try:
        scene = BabbleScene(tmp_path)
        robot, received = run_scene(orchestrator, scene, "s3")
        start_ns = orchestrator.http.get("/streams/s3").json()["start_ns"]
        onset_ns = start_ns + round(scene.person_onset_s * 1e9)
        barge_ins = [m["capture_ns"] for _, m in received if m["type"] == "barge_in"]
        assert barge_ins and barge_ins[0] < onset_ns - 2 * 10**9  # the babble's, at its start
        assert [c for c in barge_ins if abs(c - onset_ns) < 300_000_000], \
            f"no barge-in at the person's onset {scene.person_onset_s:.2f} s: " \
            f"{[(c - start_ns) / 1e9 for c in barge_ins]}"
        robot.stop()
    finally:
        orchestrator.close()


def test_an_item_is_reported_by_the_parts_that_sound():
    from esiaf_services.player.service import sounding
    pcm = np.zeros(5 * RATE, dtype=np.int16)
    pcm[RATE:2 * RATE] = 3000  # a second of sound, a 0.3 s pause, another 0.5 s, then 1.5 s of silence
    pcm[round(2.3 * RATE):round(2.8 * RATE)] = 3000
    pcm[4 * RATE:round(4.2 * RATE)] = 3000
    assert sounding(pcm, RATE) == [(RATE, round(2.8 * RATE)), (4 * RATE, round(4.2 * RATE))]
    assert sounding(np.zeros(RATE, dtype=np.int16), RATE) == []


def test_a_transcript_names_the_parts_of_a_recorded_robot_voice(tmp_path):
    from esiaf import SetupError
    from esiaf_services.player.service import Item, part_names, read_transcript
    transcript = tmp_path / "robot.json"
    transcript.write_text(json.dumps([{"start_s": 1.0, "text": "Hello."}, {"start_s": 4.0, "text": "Goodbye."}]))
    item = Item("robot.wav", np.zeros(6 * RATE), read_transcript(transcript))
    parts = [(RATE + RATE // 10, 2 * RATE), (3 * RATE, 3 * RATE + RATE // 2), (4 * RATE, 5 * RATE)]
    assert part_names(item, parts, RATE) == ["say: Hello.", "robot.wav", "say: Goodbye."]
    for bad in ('{"start_s": 1}', '[{"text": "no start"}]', "not json"):
        transcript.write_text(bad)
        with pytest.raises(SetupError, match="not a transcript"):
            read_transcript(transcript)
    with pytest.raises(SetupError, match="cannot read the transcript"):
        read_transcript(tmp_path / "missing.json")


class Talker(Component):
    """Says that speech began, as a vad does (a speech_start result, esiaf.results), when told to."""

    service = "talker"
    kind = "speech_start"

    def produce(self):
        while not self.stopping:
            self.sleep_until(time.monotonic() + 0.02)


def test_under_duck_the_rest_of_the_item_plays_lower(orchestrator, tmp_path):
    from esiaf.results import SPEECH_START, speech_start
    out = tmp_path / "loudspeaker.raw"
    robot = player(orchestrator, out, "robot")
    assert orchestrator.http.put("/streams/robot/barge-in", json={"policy": "duck"}).json() == {"policy": "duck"}
    talker = start(Talker(Talker.Settings(name="talker", orchestrator_url=orchestrator.url, stream_id="robot")))
    poll(lambda: talker.control is not None and talker.control.registration is not None, timeout_s=20)
    with connect(f"{orchestrator.ws_url}/ws/fused?stream=robot") as ws:
        assert orchestrator.http.post("/streams/robot/play", content=wav(tone(4.0, 0.5))).status_code == 202
        playing = poll(lambda: orchestrator.http.get("/streams/robot/playing").json()["playing"], timeout_s=20)
        onset_ns = playing["start_ns"] + 10**9  # a person speaks 1 s into it
        poll(lambda: time.time_ns() > onset_ns + 200_000_000, timeout_s=5)
        talker.emit(SPEECH_START, (onset_ns, onset_ns + 150_000_000), generic=speech_start(0.9))
        event = json.loads(ws.recv(timeout=10))
    assert event["type"] == "barge_in" and event["policy"] == "duck" and event["capture_ns"] == onset_ns
    poll(lambda: robot.played == 1, timeout_s=20)  # played to its end, not stopped
    played = np.frombuffer(out.read_bytes(), dtype="<i2").astype(float) / 32768
    assert len(played) == 4 * RATE
    assert np.max(np.abs(played[:RATE])) == pytest.approx(0.5, abs=0.01)
    assert np.max(np.abs(played[3 * RATE:])) == pytest.approx(0.5 * 10 ** (-15 / 20), abs=0.01)  # duck_db 15
    talker.stop()
    robot.stop()

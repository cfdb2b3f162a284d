"""Barge-in latency: from a person's speech onset, while the robot plays, to the ``barge_in`` event on the
orchestrator's websocket.

The real orchestrator (a process, a fresh SQLite file), a player following the stream (a file sink) that
plays a quiet tone for the whole run, the real Silero vad and a grabber playing a microphone file in real
time, all in this process's threads over real ZeroMQ sockets. The microphone file holds what an echo
canceller leaves: ``--questions`` RoboCup@Home questions (flite voices slt, awb, rms in turn) every
``--spacing`` s, the robot's echo cancelled entirely (the canceller's own figures are bench/aec.py's).
The stream's policy is ``ignore``, so the robot plays on and every question is a barge-in.

``--room ARRAY`` plays what the real canceller leaves instead: bench/aec.py's scene (``--seconds`` of the
robot saying flite sentences with a 5 s pause two thirds in, a person at 60° asking a RoboCup@Home question
every 8 s from 3 s, 10 dB below the robot's echo at the first microphone, babble 10 dB below the person,
the echo ``--delay`` ms late and the player's clock ``--ppm`` fast, neither told to the canceller), the
speex canceller run over it offline as bench/aec.py's ``cancel()`` does (the service's StreamCanceller and
SpeexCanceller at the service's defaults: ``residual_active_db`` 0), its first channel as the microphone
file. The player plays the scene's reference for the whole run (the pause included: a question there
counts as a barge-in too). Onsets: the same rule on the person alone at the first microphone (the scene's
truth). ``quiet`` counts questions that start where the player reports the robot not playing (a pause
of 0.5 s or more: no barge-in by design; neither found nor missed), ``robot_s`` the time it reports
playing, ``spurious_per_robot_min`` the spurious events per minute of it. ``--no-person`` leaves the
person out (no questions: every barge-in is a false one, the robot's residual and babble), ``--no-babble``
the babble; ``--rise-to 0`` runs the vad with one ``speech_start`` per stretch of speech (as before
``silero.rise_to``), ``--jump-to 0`` with a ``speech_start`` only after ``speech_start_ms`` of speech (as
before ``silero.jump_to``).

Per question: the onset is the first 10 ms frame of its clip whose level is within 30 dB of the clip's
peak (on the stream's timeline); ``latency_ms`` is the event's arrival (this host's clock, the one the
grabber stamps with) minus that onset; ``detected_ms`` the event's ``capture_ns`` (the vad's speech start)
minus the onset. A question's event is the first from 200 ms before its onset to 1 s after (none: ``missed``);
``spurious`` counts events in no question's such span (an event up to 1 s before an onset, babble just
before the question, is spurious, not the question's).

    nice -n 10 python -m bench.barge_in [--questions 8] [--spacing 4.0] [--speech-start-ms 150] [--json out.json]
    nice -n 10 python -m bench.barge_in --room respeaker4 [--seconds 60] [--delay 120] [--ppm 100] [--seed 1]
        [--no-echo] [--no-person] [--no-babble] [--rise-to 0] [--jump-to 0]

Ends with ``name=value`` lines: ``barge_in_p50_ms``, ``barge_in_p95_ms``, ``missed``, ``spurious``,
``detected_p50_ms``, ``detected_p95_ms`` (and with ``--room``: ``robot_s``, ``spurious_per_robot_min``).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import threading
import time
from pathlib import Path
from unittest import mock

import numpy as np
import soundfile
from websockets.sync.client import connect

from esiaf.tools.testing import Orchestrator, poll
from esiaf_services.grabber.service import Grabber, GrabberSettings
from esiaf_services.player.service import Player, sounding
from esiaf_services.player.tts import say
from esiaf_services.vad.service import Vad, VadSettings

RATE = 16000
QUESTIONS = ["Where is the bathroom?", "What is the capital of Germany?", "How many people are in this room?",
             "Bring me the red cup from the kitchen.", "Who invented the compact disc?",
             "What time is it?", "Follow me to the living room.", "Which is the biggest object in the kitchen?"]
VOICES = ["slt", "awb", "rms"]
EARLY_NS = 200_000_000  # a question's barge-in: an event from 200 ms before its onset to 1 s after


def onset(clip: np.ndarray) -> int:
    """The first sample of the first 10 ms frame within 30 dB of the clip's loudest frame."""
    frames = clip[:len(clip) // 160 * 160].reshape(-1, 160)
    level = 20 * np.log10(np.sqrt(np.mean(frames ** 2, axis=1)) + 1e-12)
    return int(np.argmax(level > level.max() - 30)) * 160


def scene(folder: Path, questions: int, spacing_s: float) -> tuple[Path, Path, list[float]]:
    mics = np.zeros(round((1.0 + questions * spacing_s + 2.0) * RATE))
    onsets = []
    for i in range(questions):
        clip = 0.5 * say(QUESTIONS[i % len(QUESTIONS)], VOICES[i % len(VOICES)], RATE)
        at = round((1.0 + i * spacing_s) * RATE)
        mics[at:at + len(clip)] += clip[:len(mics) - at]
        onsets.append((at + onset(clip)) / RATE)
    tone = 0.05 * np.sin(2 * np.pi * 330 * np.arange(len(mics) + 2 * RATE) / RATE)
    paths = folder / "mics.wav", folder / "robot.wav"
    soundfile.write(str(paths[0]), mics, RATE, subtype="PCM_16")
    soundfile.write(str(paths[1]), tone, RATE, subtype="PCM_16")
    return paths[0], paths[1], onsets


def room_scene(folder: Path, array: str, seconds: float, delay_ms: float, ppm: float, seed: int,
               echo: bool = True, person: bool = True,
               babble: bool = True) -> tuple[Path, Path, list[float], list[tuple[float, float]]]:
    """bench/aec.py's scene through the real canceller: its first channel, the reference (2 s longer: the
    player plays for the whole run), the person's onsets (none without the person) and the spans the
    player reports playing (s). ``echo`` False leaves the robot's echo out of the microphones (the canceller
    still gets the reference), ``person`` and ``babble`` False the person or the babble."""
    from bench.aec import cancel, render
    room = render(array, seconds, delay_ms, ppm, seed)
    mix = room.echo * echo + room.person * person + room.babble * babble + room.noise
    out, _, _ = cancel("speex", mix, room.reference, align=True)
    onsets = []
    for _, start_s, end_s in room.questions if person else []:
        first = max(0, round((start_s - 0.3) * RATE))
        onsets.append((first + onset(room.person[first:round(end_s * RATE), 0])) / RATE)
    paths = folder / "mics.wav", folder / "robot.wav"
    soundfile.write(str(paths[0]), np.clip(out[:, 0], -1, 1), RATE, subtype="PCM_16")
    soundfile.write(str(paths[1]), np.concatenate([room.reference, np.zeros(2 * RATE)]), RATE, subtype="PCM_16")
    # where the player reports the robot playing (its pauses of 0.5 s or more are not): a person starting
    # elsewhere is no barge-in, by design
    pcm = soundfile.read(str(paths[1]), dtype="int16")[0]
    return paths[0], paths[1], onsets, [(a / RATE, b / RATE) for a, b in sounding(pcm, RATE)]


def run(questions: int, spacing_s: float, speech_start_ms: float, room: dict | None = None,
        port: int = 0, rise_to: float | None = None, jump_to: float | None = None) -> dict:
    """One run: the idealised microphone file, or (``room``: room_scene's keyword arguments) the canceller's."""
    with tempfile.TemporaryDirectory(prefix="esiaf-barge-in-") as folder:
        work = Path(folder)
        spans: list[tuple[float, float]] = []
        if room is None:
            mics, robot, onsets = scene(work, questions, spacing_s)
            length_s = 1.0 + questions * spacing_s
        else:
            mics, robot, onsets, spans = room_scene(work, **room)
            length_s = room["seconds"]
        with mock.patch("esiaf.tools.testing.free_port", return_value=port) if port else contextlib.nullcontext():
            orchestrator = Orchestrator(work, config={"fusions": [{"name": "utterances", "anchor": "vad"}],
                                                      "barge_in_policy": "ignore"})
        components: list = []
        try:
            url = orchestrator.url
            player = Player(Player.Settings(name="player", orchestrator_url=url, output=str(work / "out.raw"),
                                            stream_id="bench", input=str(robot), follow_stream=True))
            silero = {**({} if rise_to is None else {"rise_to": rise_to}),
                      **({} if jump_to is None else {"jump_to": jump_to})}
            vad = Vad(VadSettings(name="vad", orchestrator_url=url, speech_start_ms=speech_start_ms, silero=silero))
            components += [player, vad]
            for component in components:
                threading.Thread(target=component.run, daemon=True).start()
            poll(lambda: all(c.control is not None and c.control.registration is not None for c in components),
                 timeout_s=60)
            arrivals: list[tuple[int, dict]] = []
            with connect(f"{orchestrator.ws_url}/ws/fused?stream=bench") as ws:
                grabber = Grabber(GrabberSettings(name="grabber", orchestrator_url=url, input=str(mics),
                                                  stream_id="bench", wait_for_subscribers=1))
                components.append(grabber)
                threading.Thread(target=grabber.run, daemon=True).start()
                deadline = time.monotonic() + length_s + 60
                while time.monotonic() < deadline:
                    message = json.loads(ws.recv(timeout=deadline - time.monotonic()))
                    arrivals.append((time.time_ns(), message))
                    if message["type"] == "stream_end":
                        break
            start_ns = orchestrator.http.get("/streams/bench").json()["start_ns"]
        finally:
            for component in components:
                component.stop()
            orchestrator.close()
    events = [(at, m) for at, m in arrivals if m["type"] == "barge_in"]
    latencies, detected, missed, quiet = [], [], 0, 0
    per_question: list[int | str | None] = []  # ms to the event, None missed, "quiet" the robot in a pause
    for onset_s in onsets:
        onset_ns = start_ns + round(onset_s * 1e9)
        if spans and not any(start <= onset_s < end for start, end in spans):
            quiet += 1  # the robot in a pause: no barge-in to expect
            per_question.append("quiet")
            continue
        near = [(at, m) for at, m in events if -EARLY_NS <= m["capture_ns"] - onset_ns < 1e9]
        per_question.append(round((near[0][0] - onset_ns) / 1e6) if near else None)
        if not near:
            missed += 1
            continue
        at, event = near[0]
        latencies.append((at - onset_ns) / 1e6)
        detected.append((event["capture_ns"] - onset_ns) / 1e6)
    spurious_s = [(m["capture_ns"] - start_ns) / 1e9 for _, m in events
                  if not any(-EARLY_NS <= m["capture_ns"] - start_ns - round(o * 1e9) < 1e9 for o in onsets)]
    robot_s = sum(end - start for start, end in spans)
    return {"mode": "idealised" if room is None else "room", "room": room, "questions": len(onsets),
            "onsets_s": onsets, "events": len(events), "quiet": quiet,
            "events_at_s": [(m["capture_ns"] - start_ns) / 1e9 for _, m in events], "missed": missed,
            "spurious": len(spurious_s), "rise_to": rise_to, "jump_to": jump_to,
            "spurious_at_s": spurious_s, "speech_start_ms": speech_start_ms, "latencies_ms": latencies,
            "detected_ms": detected, "per_question_ms": per_question,
            "barge_in_p50_ms": float(np.percentile(latencies, 50)) if latencies else None,
            "barge_in_p95_ms": float(np.percentile(latencies, 95)) if latencies else None,
            "detected_p50_ms": float(np.percentile(detected, 50)) if detected else None,
            "detected_p95_ms": float(np.percentile(detected, 95)) if detected else None,
            "robot_s": robot_s if room else None,
            "spurious_per_robot_min": len(spurious_s) / (robot_s / 60) if room and robot_s else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--questions", type=int, default=8)
    parser.add_argument("--spacing", type=float, default=4.0, help="seconds between question starts")
    parser.add_argument("--speech-start-ms", type=float, default=VadSettings().speech_start_ms,
                        help="the vad's speech_start_ms (250: at the segment's opening, min_speech_ms)")
    parser.add_argument("--rise-to", type=float, help="the vad's silero.rise_to (0: one speech_start per "
                        "stretch of speech, as before it; default: the vad's)")
    parser.add_argument("--jump-to", type=float, help="the vad's silero.jump_to (0: no speech_start before "
                        "speech_start_ms of speech, as before it; default: the vad's)")
    parser.add_argument("--room", metavar="ARRAY", help="play what the speex canceller leaves of bench/aec.py's "
                        "scene on this array (respeaker4, pepper4) instead of the idealised file")
    parser.add_argument("--seconds", type=float, default=60.0, help="--room: the scene's length")
    parser.add_argument("--delay", type=float, default=120.0, help="--room: the echo's delay after the reference, ms")
    parser.add_argument("--ppm", type=float, default=100.0, help="--room: how fast the player's clock runs")
    parser.add_argument("--seed", type=int, default=1, help="--room: the scene's seed")
    parser.add_argument("--no-echo", action="store_true", help="--room: without the robot's echo at the "
                        "microphones (the person and babble through the canceller: a control)")
    parser.add_argument("--no-person", action="store_true", help="--room: without the person (every "
                        "barge-in is a false one: the robot's residual and babble alone)")
    parser.add_argument("--no-babble", action="store_true", help="--room: without the babble")
    parser.add_argument("--port", type=int, default=0, help="the orchestrator's port (0: any free one)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    room = None if args.room is None else {"array": args.room, "seconds": args.seconds, "delay_ms": args.delay,
                                           "ppm": args.ppm, "seed": args.seed, "echo": not args.no_echo,
                                           "person": not args.no_person, "babble": not args.no_babble}
    figures = run(args.questions, args.spacing, args.speech_start_ms, room, args.port, args.rise_to,
                  args.jump_to)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))
    print("latencies_ms=" + ",".join(f"{v:.0f}" for v in figures["latencies_ms"]))
    print("per_question_ms=" + ",".join("-" if v is None else str(v) for v in figures["per_question_ms"]))
    print("detected_ms=" + ",".join(f"{v:.0f}" for v in figures["detected_ms"]))
    print("spurious_at_s=" + ",".join(f"{v:.2f}" for v in figures["spurious_at_s"]))
    for name in ("barge_in_p50_ms", "barge_in_p95_ms", "quiet", "missed", "spurious", "detected_p50_ms",
                 "detected_p95_ms", "robot_s", "spurious_per_robot_min"):
        value = figures[name]
        print(f"{name}={value:.{1 if name == 'spurious_per_robot_min' else 0}f}" if isinstance(value, float)
              else f"{name}={value}")


if __name__ == "__main__":
    main()

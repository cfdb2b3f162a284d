"""Barge-in latency: from a person's speech onset, while the robot plays, to the ``barge_in`` event on the
orchestrator's websocket.

The real orchestrator (a process, a fresh SQLite file), a player following the stream (a file sink) that
plays a quiet tone for the whole run, the real Silero vad and a grabber playing a microphone file in real
time, all in this process's threads over real ZeroMQ sockets. The microphone file holds what an echo
canceller leaves: ``--questions`` RoboCup@Home questions (flite voices slt, awb, rms in turn) every
``--spacing`` s, the robot's echo cancelled entirely (the canceller's own figures are bench/aec.py's).
The stream's policy is ``ignore``, so the robot plays on and every question is a barge-in.

Per question: the onset is the first 10 ms frame of its clip whose level is within 30 dB of the clip's
peak (on the stream's timeline); ``latency_ms`` is the event's arrival (this host's clock, the one the
grabber stamps with) minus that onset; ``detected_ms`` the event's ``capture_ns`` (the vad's speech start)
minus the onset; ``spurious`` counts events more than 1 s from every onset.

    nice -n 10 python -m bench.barge_in [--questions 8] [--spacing 4.0] [--speech-start-ms 150] [--json out.json]

Ends with ``name=value`` lines: ``barge_in_p50_ms``, ``barge_in_p95_ms``, ``missed``, ``spurious``,
``detected_p50_ms``.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import soundfile
from websockets.sync.client import connect

from esiaf.tools.testing import Orchestrator, poll
from esiaf_services.grabber.service import Grabber, GrabberSettings
from esiaf_services.player.service import Player
from esiaf_services.player.tts import say
from esiaf_services.vad.service import Vad, VadSettings

RATE = 16000
QUESTIONS = ["Where is the bathroom?", "What is the capital of Germany?", "How many people are in this room?",
             "Bring me the red cup from the kitchen.", "Who invented the compact disc?",
             "What time is it?", "Follow me to the living room.", "Which is the biggest object in the kitchen?"]
VOICES = ["slt", "awb", "rms"]


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


def run(questions: int, spacing_s: float, speech_start_ms: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="esiaf-barge-in-") as folder:
        work = Path(folder)
        mics, robot, onsets = scene(work, questions, spacing_s)
        orchestrator = Orchestrator(work, config={"fusions": [{"name": "utterances", "anchor": "vad"}],
                                                  "barge_in_policy": "ignore"})
        components: list = []
        try:
            url = orchestrator.url
            player = Player(Player.Settings(name="player", orchestrator_url=url, output=str(work / "out.raw"),
                                            stream_id="bench", input=str(robot), follow_stream=True))
            vad = Vad(VadSettings(name="vad", orchestrator_url=url, speech_start_ms=speech_start_ms))
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
                deadline = time.monotonic() + 1.0 + questions * spacing_s + 60
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
    latencies, detected, missed = [], [], 0
    for onset_s in onsets:
        onset_ns = start_ns + round(onset_s * 1e9)
        near = [(at, m) for at, m in events if abs(m["capture_ns"] - onset_ns) < 1e9]
        if not near:
            missed += 1
            continue
        at, event = near[0]
        latencies.append((at - onset_ns) / 1e6)
        detected.append((event["capture_ns"] - onset_ns) / 1e6)
    spurious = sum(all(abs(m["capture_ns"] - start_ns - round(o * 1e9)) >= 1e9 for o in onsets) for _, m in events)
    return {"questions": questions, "events": len(events), "missed": missed, "spurious": spurious,
            "speech_start_ms": speech_start_ms, "latencies_ms": latencies,
            "barge_in_p50_ms": float(np.percentile(latencies, 50)) if latencies else None,
            "barge_in_p95_ms": float(np.percentile(latencies, 95)) if latencies else None,
            "detected_p50_ms": float(np.percentile(detected, 50)) if detected else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--questions", type=int, default=8)
    parser.add_argument("--spacing", type=float, default=4.0, help="seconds between question starts")
    parser.add_argument("--speech-start-ms", type=float, default=VadSettings().speech_start_ms,
                        help="the vad's speech_start_ms (250: at the segment's opening, min_speech_ms)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    figures = run(args.questions, args.spacing, args.speech_start_ms)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))
    print("latencies_ms=" + ",".join(f"{v:.0f}" for v in figures["latencies_ms"]))
    for name in ("barge_in_p50_ms", "barge_in_p95_ms", "missed", "spurious", "detected_p50_ms"):
        value = figures[name]
        print(f"{name}={value:.0f}" if isinstance(value, float) else f"{name}={value}")


if __name__ == "__main__":
    main()

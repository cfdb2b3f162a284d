"""Live faults under ``esiaf run``, measured on examples/robocup_questions.wav (5 questions, 21 s).

    python -m bench.faults freeze [--at 3] [--for 20]      the asr SIGSTOPped, SIGCONTed later (real time)
    python -m bench.faults kill-vad [--question 1]         the vad killed (SIGKILL) in a question (real time)
    python -m bench.faults stranger [--repeats 3] [--copies 6]   a --fast replay (the example 6 times
                                                           over: 127 s) with a never-reading subscriber
                                                           on the grabber's audio port, against none

``freeze`` and ``kill-vad`` print, per question, what its fused result finally says (the text, or
the reason it has none), whether that is right, and under how many fused ids it came (more than one
is a duplicate); then the totals, the launcher's exit code and its "N fused result(s)" line.
``stranger`` prints the wall time of each replay (the stream's start to its end) without and with a
subscriber that never reads: one without the token (it is refused where the audio port takes the
token) and one with the token under a name the orchestrator never registered. The stranger connects
to the grabber's audio port (fixed for the run) before ``esiaf run`` starts, so it is there before
the replay begins however quickly that ends. Each run uses the
HTTP port ``--port`` (default 18700; ``stranger`` also the next two) and a workdir of its own. Run it
from the repository root.
"""
from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import psutil
import soundfile
import zmq

from esiaf.tools.testing import REPO, free_port, is_spare, normalise

WAV = REPO / "examples" / "robocup_questions.wav"
TRUTH = json.loads((REPO / "examples" / "robocup_questions.json").read_text())["sentences"]
RUN_TIMEOUT_S = 240.0


class Run:
    """``esiaf run --json`` on the example, as a child process; its stdout lines collected."""

    def __init__(self, port: int, workdir: Path, *more: str, wav: Path = WAV, env: dict[str, str] | None = None):
        cmd = [sys.executable, "-m", "esiaf", "run", "--input", str(wav), "--grammar", "robocup", "--json",
               "--port", str(port), "--workdir", str(workdir), *more]
        self.workdir = workdir
        self.url = f"http://127.0.0.1:{port}"
        self.process = subprocess.Popen(["nice", "-n", "10", *cmd], cwd=REPO, text=True, stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE,
                                        env={**os.environ, **(env or {}), "PYTHONPATH": str(REPO)})
        self.lines: list[dict] = []
        self.stderr: list[str] = []
        self.started = threading.Event()  # the grabber plays: stream_start printed
        self.started_at = self.ended_at = 0.0
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=lambda: self.stderr.extend(self.process.stderr or ()), daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout or ():
            if not line.startswith("{"):
                continue
            message = json.loads(line)
            self.lines.append(message)
            if message.get("type") == "stream_start":
                self.started_at = time.monotonic()
                self.started.set()
            elif message.get("type") == "stream_end":
                self.ended_at = time.monotonic()

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {(self.workdir / 'token').read_text().strip()}"}

    def pid(self, service: str) -> int:
        """The process of ``service`` (``esiaf_services.<service>`` on its command line)."""
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and self.process.poll() is None:
            for child in psutil.Process(self.process.pid).children(recursive=True):
                try:
                    if f"esiaf_services.{service}" in " ".join(child.cmdline()) and not is_spare(child):
                        return child.pid
                except psutil.Error:
                    continue
            time.sleep(0.1)
        raise RuntimeError(f"no {service} process: " + "".join(self.stderr[-10:]))

    def back(self, service: str, old_pid: int) -> float | None:
        """Seconds into the file when a new instance of ``service`` (another process) registered."""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and self.process.poll() is None:
            try:
                items = httpx.get(f"{self.url}/components", headers=self.headers, timeout=10).json()["items"]
            except (httpx.HTTPError, ValueError, KeyError):
                items = []
            found = [c for c in items if c["name"] == service and c.get("pid") not in (None, old_pid)]
            if found:
                return time.monotonic() - self.started_at
            time.sleep(0.1)
        return None

    def wait(self) -> int:
        try:
            return self.process.wait(timeout=RUN_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.process.send_signal(signal.SIGINT)
            return self.process.wait(timeout=30)

    def at(self, seconds: float) -> None:
        """Sleeps until ``seconds`` after the grabber started playing."""
        if not self.started.wait(timeout=180):
            raise RuntimeError("the grabber never started: " + "".join(self.stderr[-20:]))
        time.sleep(max(0.0, self.started_at + seconds - time.monotonic()))


def outcome(fused: dict) -> str:
    """What a fused result's latest revision says: its text, or why it has none."""
    anchor = fused["anchor"]
    hypotheses = anchor.get("speech", {}).get("hypotheses") or []
    if hypotheses:
        return normalise(hypotheses[0].get("text", "")) or "(not understood)"
    if "nothing" in anchor:
        return f"(lost: {anchor['nothing'].get('reason', '')})"
    missing = [m for m in fused.get("missing", []) if m.get("type") == "speech"]
    return f"(lost: recogniser {missing[0]['reason']})" if missing else "(no text, no reason)"


def report(run: Run, code: int) -> None:
    start = next((m["start_ns"] for m in run.lines if m.get("type") == "stream_start"), 0)
    latest: dict[int, dict] = {}
    for message in run.lines:
        if message.get("type") == "fused_result":
            latest[message["id"]] = message  # in publication order: the last is the latest revision
    totals = {"right": 0, "with_reason": 0, "wrong": 0, "silent": 0, "duplicated": 0}
    for n, truth in enumerate(TRUTH, start=1):
        span = (start + round(truth["start_s"] * 1e9), start + round(truth["end_s"] * 1e9))
        ids = [i for i, f in latest.items() if f["anchor"]["span"]["start_ns"] < span[1]
               and f["anchor"]["span"]["end_ns"] > span[0]]
        said = [f"{outcome(latest[i])} rev {latest[i]['revision']}" for i in ids]
        if not ids:
            totals["silent"] += 1
        elif any(outcome(latest[i]) == normalise(truth["text"]) for i in ids):
            totals["right"] += 1
        elif all(outcome(latest[i]).startswith("(lost") for i in ids):
            totals["with_reason"] += 1
        else:
            totals["wrong"] += 1
        totals["duplicated"] += len(ids) > 1
        print(f"question_{n}={normalise(truth['text'])!r} fused_ids={ids} said={said}")
    printed = next((line.strip() for line in run.stderr if "fused result(s)" in line), "no stream end")
    print(" ".join(f"{k}={v}" for k, v in totals.items()), f"fused_ids={len(latest)}", f"exit={code}",
          f"launcher={printed!r}")


def freeze(args: argparse.Namespace, workdir: Path) -> None:
    run = Run(args.port, workdir)
    pid = run.pid("asr")
    run.at(args.at)
    os.kill(pid, signal.SIGSTOP)
    print(f"asr pid={pid} stopped at {time.monotonic() - run.started_at:.1f} s")
    try:
        run.at(args.at + args.seconds)
    finally:
        os.kill(pid, signal.SIGCONT)
    print(f"asr continued at {time.monotonic() - run.started_at:.1f} s")
    report(run, run.wait())


def kill_vad(args: argparse.Namespace, workdir: Path) -> None:
    run = Run(args.port, workdir)
    pid = run.pid("vad")
    question = TRUTH[args.question - 1]
    run.at((question["start_s"] + question["end_s"]) / 2)  # in the middle of the question
    os.kill(pid, signal.SIGKILL)
    print(f"vad pid={pid} killed at {time.monotonic() - run.started_at:.2f} s (question {args.question}: "
          f"{question['start_s']:.2f}-{question['end_s']:.2f} s)", flush=True)
    back_s = run.back("vad", pid)
    print(f"vad back (its new instance registered) at {back_s:.2f} s" if back_s else "vad never back")
    report(run, run.wait())
    print("launcher said:", " | ".join(line.strip() for line in run.stderr if "vad" in line))


def stranger(args: argparse.Namespace, workdir: Path) -> None:
    """A --fast replay's wall time without a stranger, with one without the token, with one with it."""
    samples, rate = soundfile.read(str(WAV), dtype="int16")
    wav = workdir / "copies.wav"
    soundfile.write(str(wav), np.tile(samples, args.copies), rate, subtype="PCM_16")
    times: dict[str, list[float]] = {"none": [], "no_token": [], "token_unregistered": []}
    for repeat in range(args.repeats):
        for n, (kind, found) in enumerate(times.items()):
            audio_port, token = free_port(), secrets.token_hex(16)
            context = zmq.Context()
            try:  # connected before the grabber binds: ZeroMQ retries until it does
                kept = subscribe(context, audio_port, token if kind == "token_unregistered" else None) \
                    if kind != "none" else None
                run = Run(args.port + n, workdir / f"{kind}-{repeat}", "--fast", "--without", "emotion,gender,voiceid",
                          wav=wav, env={"ESIAF_GRABBER_AUDIO_PORT": str(audio_port), "ESIAF_TOKEN": token})
                code = run.wait()
                del kept
                took = run.ended_at - run.started_at if run.ended_at else float("nan")
                found.append(took)
                print(f"run={kind} repeat={repeat} exit={code} replay_s={took:.2f}", flush=True)
            finally:
                context.destroy(linger=0)
    for kind, found in times.items():
        print(f"{kind}: replay_s median={sorted(found)[len(found) // 2]:.2f} all={[round(t, 2) for t in found]}")


def subscribe(context: zmq.Context, audio_port: int, token: str | None) -> zmq.Socket:
    """Subscribes to everything on the grabber's audio port (before it is bound), and never reads (a queue
    of one message and the smallest kernel buffer: it stalls as soon as it can)."""
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.RCVHWM, 1)
    sub.setsockopt(zmq.RCVBUF, 4096)
    if token is not None:
        sub.plain_username = b"stranger"
        sub.plain_password = token.encode()
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(f"tcp://127.0.0.1:{audio_port}")
    return sub  # kept by the caller: a socket garbage-collected is closed


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.faults", description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, default=18700, help="the orchestrator's HTTP port")
    sub = parser.add_subparsers(dest="scenario", required=True)
    frozen = sub.add_parser("freeze")
    frozen.add_argument("--at", type=float, default=3.0, help="seconds into the file")
    frozen.add_argument("--for", dest="seconds", type=float, default=20.0, help="how long the asr stays stopped")
    killed = sub.add_parser("kill-vad")
    killed.add_argument("--question", type=int, default=1, choices=range(1, len(TRUTH) + 1))
    strange = sub.add_parser("stranger")
    strange.add_argument("--repeats", type=int, default=3)
    strange.add_argument("--copies", type=int, default=6, help="the example this many times over")
    parser.add_argument("--workdir", type=Path, help="keep each run's workdir (its logs) here; default: a "
                        "temporary folder, removed")
    args = parser.parse_args()
    scenario = {"freeze": freeze, "kill-vad": kill_vad, "stranger": stranger}[args.scenario]
    if args.workdir is not None:
        scenario(args, args.workdir.resolve())
        return
    with tempfile.TemporaryDirectory(prefix="esiaf-faults-") as tmp:
        scenario(args, Path(tmp))


if __name__ == "__main__":
    main()

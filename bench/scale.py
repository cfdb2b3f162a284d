"""Streams at once: how many real-time streams the pipeline keeps within 1 s, replicas
that lose only what was in flight on a killed one, and a skewed clock.

Every run starts its own orchestrator, vad (silero), ``--asr`` pocketsphinx instances with the
RoboCup grammar (no emotion, gender or voiceid) and one grabber process per stream, each playing
its own flite-spoken RoboCup questions in real time. The streams start 0.7 s apart, so that their
utterances do not all end at once. A fused result's latency is the moment its JSON reaches this
process's websocket minus (the capture time of the utterance's last speech sample + the VAD's
hangover), as in bench/latency.py.

Per run it reports, over all streams: questions played, fused results, questions with no fused
result overlapping them (``lost``: silently), questions fused without their recogniser because it
died with them in flight or, past saturation, passed them by (``reported_lost``), questions
recognised exactly (``right``), fused results not ``complete``, and the p50/p95/max latency.

    python bench/scale.py [--streams 1,2,3,4,6,8] [--questions 6]     # the sweep
    python bench/scale.py --kill [--asr 3 --streams 8]                 # kill one asr mid-run
    python bench/scale.py --skew 3                                     # the vad's clock 3 s ahead

``max_streams_p95_le_1s`` is the largest swept number of streams whose p95 is ≤ 1 s with nothing
lost. With ``--kill``, the asr instance serving the most streams is SIGKILLed halfway through and
reported dead as ``esiaf run`` does; the figures are split into before and after the kill.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]  # its modules are bench.NAME
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from synth_questions import DEFAULT_QUESTIONS, read_questions, synthesise_to_wav  # noqa: E402

from esiaf import auth  # noqa: E402
from esiaf.speech.segmenter import SegmenterParams  # noqa: E402
from esiaf.tools.feed import FusedFeed  # noqa: E402
from esiaf.tools.launcher import OrchestratorClient, Supervisor, fixed_ports, wait_until  # noqa: E402
from esiaf.tools.robocup_scoring import normalise  # noqa: E402

HANGOVER_NS = int(SegmenterParams().keep_alive_ms * 1_000_000)
STAGGER_S = 0.7  # between the streams' starts


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q * 100)) if values else float("nan")  # linear, as bench/latency.py


@dataclass
class Stream:
    stream_id: str
    wav: Path
    truth: list[dict]  # {text, start_s, end_s}
    start_ns: int = 0
    fused: list[dict] = field(default_factory=list)  # first publications, with "arrived_ns"
    ended: bool = False


def make_inputs(count: int, questions: int, work: Path) -> list[Stream]:
    """``count`` files of ``questions`` questions each (different questions per stream, as far as
    the 50 go), spoken by flite."""
    pool = sorted(read_questions(DEFAULT_QUESTIONS).items())
    streams = []
    for i in range(count):
        chosen = [pool[(i * questions + k) % len(pool)] for k in range(questions)]
        wav = work / f"stream{i}.wav"
        truths = synthesise_to_wav(chosen, wav)
        streams.append(Stream(f"s{i}", wav, [{"text": t.text, "start_s": t.start_s, "end_s": t.end_s} for t in truths]))
    return streams


class Pipeline:
    """orchestrator + vad + asr instances as processes of one supervisor, on their own workdir."""

    def __init__(self, port: int, asr: int, env: dict[str, dict[str, str]]) -> None:
        self.workdir = Path(tempfile.mkdtemp(prefix="esiaf-scale-"))
        self.url = f"http://127.0.0.1:{port}"
        os.environ[auth.TOKEN_ENV] = auth.new_token()
        self.supervisor = Supervisor(self.workdir, env={"ESIAF_ORCHESTRATOR_URL": self.url})
        self.client = OrchestratorClient(self.url)
        ports = fixed_ports(self.workdir)
        orchestrator = self.supervisor.start("orchestrator", ["--port", str(port), "--db", str(self.workdir / "db")],
                                             env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": str(ports["control"]),
                                                  "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(ports["results"])})
        wait_until(self.client.healthy, self.supervisor, "the orchestrator", 60, orchestrator)
        self.supervisor.start("vad", env=env.get("vad"))
        self.asr = [self.supervisor.start("asr", ["--grammar", "robocup"], env=env.get("asr"), instance=f"asr-{i + 1}")
                    for i in range(asr)]
        wait_until(lambda: sum(c.get("status") == "alive" for c in self.client.components()) == 1 + asr,
                   self.supervisor, "vad and asr to register", 90)

    def play(self, streams: list[Stream]) -> None:
        for i, stream in enumerate(streams):
            if i:
                time.sleep(STAGGER_S)
            self.supervisor.start("grabber", ["--input", str(stream.wav)], instance=f"grabber-{i}",
                                  env={"ESIAF_STREAM_ID": stream.stream_id, "ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"})

    def serving(self) -> dict[str, str]:
        response = self.client._http.get(f"{self.url}/components")
        return response.json()["services"].get("asr", {}).get("serving", {})

    def stop(self) -> None:
        self.client.close()
        self.supervisor.stop()


def collect(url: str, streams: list[Stream], deadline: float, stop: threading.Event) -> None:
    by_id = {s.stream_id: s for s in streams}
    with FusedFeed(url.replace("http", "ws", 1) + "/ws/fused?fusion=speech") as feed:
        while not stop.is_set() and time.monotonic() < deadline and not all(s.ended for s in streams):
            try:
                text = feed.recv(timeout=0.5)
            except TimeoutError:
                continue
            arrived_ns = time.time_ns()
            message = json.loads(text)
            stream = by_id.get(message.get("stream_id", ""))
            if stream is None:
                continue
            if message.get("type") == "stream_end":
                stream.ended = True
            elif message.get("type") == "fused_result" and message.get("revision", 1) == 1:
                stream.fused.append({**message, "arrived_ns": arrived_ns})


def score(streams: list[Stream], since_ns: int = 0, until_ns: int = 2**63) -> dict[str, float]:
    """Figures over the questions that ended within [since_ns, until_ns) (capture time)."""
    played = lost = right = incomplete = orphaned = 0
    latencies: list[float] = []
    for stream in streams:
        for question in stream.truth:
            q_start = stream.start_ns + int(question["start_s"] * 1e9)
            q_end = stream.start_ns + int(question["end_s"] * 1e9)
            if not since_ns <= q_end < until_ns:
                continue
            played += 1
            hits = [f for f in stream.fused if f["anchor"]["span"]["start_ns"] < q_end
                    and f["anchor"]["span"]["end_ns"] > q_start]
            if not hits:
                lost += 1
                continue
            hit = hits[0]
            orphaned += hit["anchor"]["type"] != "speech"  # fused without its recogniser: reported lost
            hyps = hit["anchor"].get("speech", {}).get("hypotheses", [])
            right += bool(hyps) and normalise(hyps[0]["text"]) == normalise(question["text"])
            incomplete += hit.get("completion") != "complete"
            latencies.append((hit["arrived_ns"] - hit["anchor"]["span"]["end_ns"] - HANGOVER_NS) / 1e6)
    return {"questions": played, "lost": lost, "reported_lost": orphaned, "right": right, "incomplete": incomplete,
            "fused": len(latencies), "p50_ms": percentile(latencies, 0.5),
            "p95_ms": percentile(latencies, 0.95), "max_ms": max(latencies, default=float("nan"))}


def run(count: int, questions: int, asr: int, port: int, work: Path, kill: bool = False,
        env: dict[str, dict[str, str]] | None = None) -> dict[str, dict[str, float]]:
    streams = make_inputs(count, questions, work)
    pipeline = Pipeline(port, asr, env or {})
    stop = threading.Event()
    length_s = max(float(json.loads(s.wav.with_suffix(".json").read_text())["duration_s"]) for s in streams)
    collector = threading.Thread(target=collect, args=(pipeline.url, streams, time.monotonic() + length_s
                                                       + count * STAGGER_S + 120, stop), daemon=True)
    try:
        collector.start()
        time.sleep(1.0)  # the websocket is open before the first result
        pipeline.play(streams)
        for stream in streams:
            info = wait_until(functools.partial(pipeline.client.stream, stream.stream_id), pipeline.supervisor,
                              f"stream {stream.stream_id}", 60)
            stream.start_ns = info["start_ns"]
        killed_ns, victim = 0, ""
        if kill:
            time.sleep(length_s / 2)
            serving = pipeline.serving()
            victim = max(set(serving.values()), key=list(serving.values()).count)
            child = next(c for c in pipeline.asr if c.name == victim)
            child.process.send_signal(signal.SIGKILL)
            killed_ns = time.time_ns()
            child.process.wait()
            pipeline.client.report_dead(child.process.pid)  # as esiaf run does when it sees a service die
            print(f"killed {victim} (serving {sorted(s for s, i in serving.items() if i == victim)})",
                  file=sys.stderr, flush=True)
        collector.join()
    finally:
        stop.set()
        pipeline.stop()
    if not all(s.ended for s in streams):
        print(f"streams without stream_end: {[s.stream_id for s in streams if not s.ended]}", file=sys.stderr)
    if kill:
        return {"before": score(streams, until_ns=killed_ns), "after": score(streams, since_ns=killed_ns)}
    return {"all": score(streams)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--streams", default="1,2,3,4,6,8", help="numbers of concurrent streams to try (sweep), "
                        "or the number of streams with --kill/--skew")
    parser.add_argument("--questions", type=int, default=6, help="questions per stream (6)")
    parser.add_argument("--asr", type=int, default=1, help="asr instances (1; 3 with --kill)")
    parser.add_argument("--kill", action="store_true", help="kill the busiest asr instance halfway through")
    parser.add_argument("--skew", type=float, help="the vad's clock this many seconds off (test-only clock_skew_s)")
    parser.add_argument("--port", type=int, default=8140)
    args = parser.parse_args()
    if not DEFAULT_QUESTIONS.exists():
        raise SystemExit(f"needs the RoboCup questions in {DEFAULT_QUESTIONS} (../shared/data)")
    counts = [int(c) for c in args.streams.split(",")]
    work = Path(tempfile.mkdtemp(prefix="esiaf-scale-inputs-"))
    figures: dict[str, float] = {}
    if args.kill or args.skew is not None:
        count = counts[-1] if args.streams != parser.get_default("streams") else (8 if args.kill else 1)
        asr = args.asr if args.asr != 1 or not args.kill else 3
        env = {"vad": {"ESIAF_VAD_CLOCK_SKEW_S": str(args.skew)}} if args.skew is not None else {}
        print(f"{count} streams, {asr} asr{' , killing one' if args.kill else ''} ...", file=sys.stderr, flush=True)
        for part, values in run(count, args.questions, asr, args.port, work, args.kill, env).items():
            figures.update({f"{part}_{k}": v for k, v in values.items()})
    else:
        best = 0
        for count in counts:
            print(f"{count} streams, {args.asr} asr ...", file=sys.stderr, flush=True)
            values = run(count, args.questions, args.asr, args.port, work)["all"]
            figures.update({f"streams{count}_{k}": v for k, v in values.items()})
            print(" ".join(f"{k}={v:.0f}" for k, v in values.items()), file=sys.stderr, flush=True)
            if values["lost"] == 0 and values["p95_ms"] <= 1000:
                best = max(best, count)
        figures["max_streams_p95_le_1s"] = best
    for name, value in figures.items():
        print(f"{name}={value:.1f}" if isinstance(value, float) else f"{name}={value}")


if __name__ == "__main__":
    main()

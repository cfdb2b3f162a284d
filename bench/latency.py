"""End-of-speech-to-result latency: the full pipeline beside a monolithic baseline, in one run.

Both play the same file in real time, in 20 ms chunks stamped from sample counts:

- pipeline: ``esiaf run --json --serve`` (grabber → vad → asr → orchestrator → websocket client);
  a result's arrival is the moment its JSON line reaches this process;
- baseline: the same segmenter and the same pocketsphinx recogniser in this one process, no
  transport; a result's arrival is the moment the recogniser returns.

Latency = arrival − (capture time of the utterance's last speech sample + the VAD hangover),
i.e. from the earliest moment any segmenter could know the utterance ended. It prints
``name=value`` lines at the end; CPU is per component, per minute of audio (psutil).

    python bench/latency.py [--questions 20 | --input FILE] [--grammar robocup|FILE|''] [--port 8123]

By default it synthesises 20 RoboCup questions with flite (2.5 s of silence between them) from
../shared/data/robocup/questions.tsv; without flite or the data it plays examples/robocup_questions.wav.
CPU figures are measured while the audio plays (start-up, i.e. imports and model loading, is
reported apart as ``startup_cpu_s_<service>``).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import soundfile

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.audio import SampleClock  # noqa: E402
from esiaf.formats import AudioFormat, peak  # noqa: E402
from services.asr.recognizer import PocketsphinxRecognizer  # noqa: E402
from services.asr.service import resolve_grammar  # noqa: E402
from services.vad.segmenter import Segmenter, SegmenterParams, level_db  # noqa: E402

CHUNK_MS = 20
HANGOVER_NS = int(SegmenterParams().keep_alive_ms * 1_000_000)


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    k = (len(ordered) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


def baseline(path: Path, grammar: str) -> tuple[list[float], list[str], float]:
    """Segmenter + recogniser in one loop, paced in real time. Returns latencies (ms), texts, CPU s."""
    audio, rate = soundfile.read(str(path), dtype="int16", always_2d=True)
    fmt = AudioFormat(rate, "int16")
    recognizer = PocketsphinxRecognizer(sample_rate_hz=rate, grammar=resolve_grammar(grammar))
    segmenter: Segmenter[bytes] = Segmenter(SegmenterParams())
    step = rate * CHUNK_MS // 1000
    cpu_start = time.process_time()
    origin_ns, started = time.time_ns(), time.monotonic()
    clock = SampleClock(origin_ns, rate)
    latencies, texts, open_utterance = [], [], False
    for offset in range(0, len(audio), step):
        chunk = audio[offset:offset + step]
        start_ns, end_ns = clock.advance(len(chunk))
        delay = started + (end_ns - origin_ns) / 1e9 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        last = offset + step >= len(audio)
        for forward in segmenter.process(chunk.tobytes(), start_ns, end_ns, level_db(peak(chunk, fmt)),
                                         force_end=last):
            if not open_utterance:
                recognizer.start()
                open_utterance = True
            recognizer.feed(forward.item)
            if forward.ended:
                hypotheses = recognizer.finish()
                open_utterance = False
                latencies.append((time.time_ns() - forward.segment[1] - HANGOVER_NS) / 1e6)
                texts.append(hypotheses[0].text if hypotheses else "")
    return latencies, texts, time.process_time() - cpu_start


def pipeline(path: Path, grammar: str, port: int) -> tuple[list[float], list[str], dict[str, float]]:
    """The launcher with every service as a process. Returns latencies (ms), texts, CPU s per service."""
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-bench-"))
    cmd = [sys.executable, "-m", "esiaf.cli", "run", "--input", str(path), "--json", "--serve",
           "--port", str(port), "--workdir", str(workdir)] + (["--grammar", grammar] if grammar else [])
    launcher = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONPATH": str(REPO)})
    latencies, texts = [], []
    ended = threading.Event()
    cpu_at_start: dict[str, float] = {}
    stderr_lines: list[str] = []

    def read_stdout() -> None:
        for line in launcher.stdout:
            arrived_ns = time.time_ns()
            fused = json.loads(line)
            if fused.get("type") == "stream_start":
                cpu_at_start.update(children_cpu(launcher.pid))
            if fused.get("type") != "fused_result":
                continue
            anchor = fused["anchor"]
            latencies.append((arrived_ns - anchor["span"]["end_ns"] - HANGOVER_NS) / 1e6)
            hyps = anchor.get("speech", {}).get("hypotheses", [])
            texts.append(hyps[0]["text"] if hyps else "")

    def read_stderr() -> None:
        for line in launcher.stderr:
            stderr_lines.append(line)
            if "stream ended" in line:
                ended.set()

    threads = [threading.Thread(target=f, daemon=True) for f in (read_stdout, read_stderr)]
    for thread in threads:
        thread.start()
    info = soundfile.info(str(path))
    if not ended.wait(timeout=info.duration + 120) or launcher.poll() is not None:
        launcher.kill()
        raise SystemExit("pipeline did not finish:\n" + "".join(stderr_lines))
    cpu_at_end = children_cpu(launcher.pid)
    launcher.send_signal(signal.SIGINT)
    launcher.wait(timeout=30)
    return latencies, texts, {name: cpu_at_end[name] - cpu_at_start.get(name, 0.0) for name in cpu_at_end}, \
        cpu_at_start


def children_cpu(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) so far of each service the launcher started."""
    cpu = {}
    for child in psutil.Process(pid).children():
        name = next((a.split(".", 1)[1] for a in child.cmdline() if a.startswith("services.")), str(child.pid))
        times = child.cpu_times()
        cpu[name] = times.user + times.system
    return cpu


def synthesised_input(count: int) -> Path | None:
    """``count`` RoboCup questions spoken by flite, or None without flite or the shared data."""
    sys.path.insert(0, str(REPO / "scripts"))
    from synth_questions import DEFAULT_QUESTIONS, SynthesisError, read_questions, synthesise_to_wav
    if not DEFAULT_QUESTIONS.exists():
        return None
    questions = read_questions(DEFAULT_QUESTIONS)
    chosen = [(i, questions[i]) for i in sorted(questions)[:count]]
    path = Path(tempfile.mkdtemp(prefix="esiaf-bench-")) / "questions.wav"
    try:
        synthesise_to_wav(chosen, path)
    except SynthesisError as exc:
        print(f"cannot synthesise the input ({exc}); using the example file", file=sys.stderr)
        return None
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--input", type=Path, help="a 16 kHz mono file instead of synthesised questions")
    parser.add_argument("--questions", type=int, default=20, help="how many questions to synthesise (20)")
    parser.add_argument("--grammar", default="robocup", help="robocup (default), a JSGF file, or '' for the LM")
    parser.add_argument("--port", type=int, default=8123)
    args = parser.parse_args()
    if args.input is None:
        args.input = synthesised_input(args.questions) or REPO / "examples" / "robocup_questions.wav"
    minutes = soundfile.info(str(args.input)).duration / 60

    print(f"baseline: playing {args.input} in real time ...", file=sys.stderr, flush=True)
    base_ms, base_texts, base_cpu = baseline(args.input, args.grammar)
    print(f"pipeline: playing {args.input} in real time ...", file=sys.stderr, flush=True)
    pipe_ms, pipe_texts, pipe_cpu, startup_cpu = pipeline(args.input, args.grammar, args.port)

    for name, texts in (("baseline", base_texts), ("pipeline", pipe_texts)):
        print(f"{name} texts: {texts}", file=sys.stderr)
    figures = {
        "audio_s": minutes * 60,
        "utterances_baseline": len(base_ms), "utterances_pipeline": len(pipe_ms),
        "same_texts": int(base_texts == pipe_texts),
        "baseline_p50_ms": percentile(base_ms, 0.5), "baseline_p95_ms": percentile(base_ms, 0.95),
        "pipeline_p50_ms": percentile(pipe_ms, 0.5), "pipeline_p95_ms": percentile(pipe_ms, 0.95),
        "overhead_p50_ms": percentile(pipe_ms, 0.5) - percentile(base_ms, 0.5),
        "overhead_p95_ms": percentile(pipe_ms, 0.95) - percentile(base_ms, 0.95),
        "baseline_cpu_s_per_min": base_cpu / minutes,
    }
    for name, seconds in sorted(pipe_cpu.items()):
        figures[f"cpu_s_per_min_{name}"] = seconds / minutes
    figures["pipeline_cpu_s_per_min_total"] = sum(pipe_cpu.values()) / minutes
    for name, seconds in sorted(startup_cpu.items()):
        figures[f"startup_cpu_s_{name}"] = seconds
    for name, value in figures.items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}")


if __name__ == "__main__":
    main()

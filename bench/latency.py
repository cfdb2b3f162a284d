"""End-of-speech-to-fused-line latency: the pipeline beside a monolithic baseline, in one run.

All play the same file in real time, in chunks of the grabber's default length (chunk_ms) stamped
from sample counts:

- pipeline ``full``: ``esiaf run --json --serve`` as a user runs it (grabber → vad → asr, emotion,
  gender [+ splitter, ssl with --array] → orchestrator fusing them → websocket client); a
  result's arrival is the moment its fused JSON line reaches this process;
- pipeline ``asr``: the same with ``--without emotion,gender,voiceid`` (what a slow robot would run);
- baseline: the same segmenter (Silero; per window unless ESIAF_VAD_SILERO__WINDOWS=false), the same
  pocketsphinx recogniser and the same emotion and gender models in this one process, no
  transport, one after the other; ``baseline_asr`` is the moment
  the recogniser returns, ``baseline_full`` the moment the gender model (the last) returns.

Latency = arrival − (capture time of the utterance's last speech sample + the VAD hangover),
i.e. from the earliest moment any segmenter could know the utterance ended. It prints
``name=value`` lines at the end; CPU is per component, per minute of audio (psutil).
With ``--array`` (a multi-channel input such as the demo scene) the pipelines also run the
splitter and ssl (the baseline does no SSL: it hears channel 0 only).

    python bench/latency.py [--questions 20 | --input FILE [--array SPEC]] [--grammar robocup|FILE|'']
                            [--variants full,asr] [--port 8123]

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
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import psutil
import soundfile

REPO = Path(__file__).resolve().parent.parent
# the repository first, bench/ itself not on the path (its modules are bench.NAME)
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]
sys.path.insert(0, str(REPO))

from bench.monolith import monolith  # noqa: E402
from esiaf.speech.segmenter import SegmenterParams  # noqa: E402
from esiaf.tools.testing import is_spare  # noqa: E402

HANGOVER_NS = int(SegmenterParams().keep_alive_ms * 1_000_000)


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    k = (len(ordered) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


def baseline(path: Path, grammar: str) -> tuple[dict[str, list[float]], list[str], float]:
    """The monolith (bench/monolith.py: the Silero VAD deciding as the pipeline's does, per window, or
    per chunk with ESIAF_VAD_SILERO__WINDOWS=false; recogniser, emotion and gender models in one loop), paced
    in real time, on the first channel. Returns latencies (ms) after the recogniser ("asr") and after
    all ("full"), texts, CPU s."""
    windows = os.environ.get("ESIAF_VAD_SILERO__WINDOWS", "true").lower() not in ("0", "false")  # as the pipeline's vad
    run = monolith(path, grammar, vad="silero", windows=windows)
    latencies: dict[str, list[float]] = {"asr": [], "full": []}
    for utterance in run.utterances:
        latencies["asr"].append((utterance.done_ns["asr"] - utterance.end_ns - HANGOVER_NS) / 1e6)
        latencies["full"].append((utterance.done_ns["all"] - utterance.end_ns - HANGOVER_NS) / 1e6)
    return latencies, [u.text for u in run.utterances], sum(run.cpu_s.values())


def pipeline(path: Path, grammar: str, port: int, extra: list[str], workdir: Path | None = None,
             on_ended: Callable[[], None] | None = None, progress_s: float = 0.0,
             on_start: Callable[[dict[str, int]], None] | None = None, repo: Path = REPO,
             env: dict[str, str] | None = None):
    """The launcher with every service as a process. Returns latencies (ms), texts, CPU s per
    service while playing, CPU s per service at start-up, and the fused results (with the moment
    each arrived, ``arrived_ns``, and the stream's start, ``stream_start_ns``). ``on_ended`` is
    called once the stream has ended, before the services stop; with ``progress_s`` a line on
    stderr says that often how many fused results have come; ``on_start`` is called with each
    service's process id when the stream starts (bench/framework.py's profiler); ``repo`` is the
    checkout whose code runs (this one unless another is compared with it); ``env``: more environment
    variables for every process (e.g. an orchestrator setting)."""
    workdir = workdir or Path(tempfile.mkdtemp(prefix="esiaf-bench-"))
    cmd = [sys.executable, "-m", "esiaf", "run", "--input", str(path), "--json", "--serve",
           "--port", str(port), "--workdir", str(workdir), *extra] + (["--grammar", grammar] if grammar else [])
    launcher = subprocess.Popen(cmd, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, **(env or {}), "PYTHONPATH": str(repo)},
                                # Ctrl-C stops it even when the bench runs in the background
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    latencies, texts, fused_results = [], [], []
    ended = threading.Event()
    cpu_at_start: dict[str, float] = {}
    stream_start_ns: list[int] = []
    stderr_lines: list[str] = []

    def read_stdout() -> None:
        assert launcher.stdout is not None  # stdout=PIPE
        for line in launcher.stdout:
            arrived_ns = time.time_ns()
            fused = json.loads(line)
            if fused.get("type") == "stream_start":
                stream_start_ns.append(fused["start_ns"])
                cpu_at_start.update(children_cpu(launcher.pid))
                if on_start is not None:
                    on_start(service_pids(launcher.pid))
            if fused.get("type") != "fused_result":
                continue
            if fused.get("revision", 1) > 1:
                continue  # a revision of a result already counted: its latency is the first publication's
            fused_results.append({**fused, "arrived_ns": arrived_ns, "stream_start_ns": stream_start_ns[-1]})
            anchor = fused["anchor"]
            latencies.append((arrived_ns - anchor["span"]["end_ns"] - HANGOVER_NS) / 1e6)
            hyps = anchor.get("speech", {}).get("hypotheses", [])
            texts.append(hyps[0]["text"] if hyps else "")

    def read_stderr() -> None:
        assert launcher.stderr is not None  # stderr=PIPE
        for line in launcher.stderr:
            stderr_lines.append(line)
            if "stream ended" in line:
                ended.set()

    threads = [threading.Thread(target=f, daemon=True) for f in (read_stdout, read_stderr)]
    for thread in threads:
        thread.start()
    started = time.monotonic()
    deadline, report = started + soundfile.info(str(path)).duration + 120, started + progress_s
    seen: dict[str, float] = {}  # a service that exits at the stream's end (the grabber) is gone by then
    while not ended.wait(timeout=0.5) and launcher.poll() is None and time.monotonic() < deadline:
        seen.update(children_cpu(launcher.pid))
        if progress_s and time.monotonic() >= report:
            report += progress_s
            print(f"pipeline: {len(fused_results)} fused after {time.monotonic() - started:.0f} s",
                  file=sys.stderr, flush=True)
    if not ended.is_set() or launcher.poll() is not None:
        launcher.kill()
        raise SystemExit("pipeline did not finish:\n" + "".join(stderr_lines))
    cpu_at_end = {**seen, **children_cpu(launcher.pid)}
    if on_ended is not None:
        on_ended()
    launcher.send_signal(signal.SIGINT)
    try:
        launcher.wait(timeout=30)
    except subprocess.TimeoutExpired:
        launcher.terminate()  # its services get SIGTERM with it (PR_SET_PDEATHSIG)
        launcher.wait(timeout=30)
    return latencies, texts, {name: cpu_at_end[name] - cpu_at_start.get(name, 0.0) for name in cpu_at_end}, \
        cpu_at_start, fused_results


def services(pid: int) -> dict[str, psutil.Process]:
    """Each service the launcher started (and still running), by name."""
    found = {}
    for child in psutil.Process(pid).children():
        try:
            name = next((a.split(".", 1)[1] for a in child.cmdline() if a.startswith("esiaf_services.")),
                        str(child.pid))
            found[f"{name}-spare" if is_spare(child) else name] = child  # a spare's cost apart
        except psutil.NoSuchProcess:  # it exited meanwhile
            continue
    return found


def service_pids(pid: int) -> dict[str, int]:
    return {name: child.pid for name, child in services(pid).items()}


def children_cpu(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) so far of the launcher and of each service it started."""
    launcher = psutil.Process(pid)
    times = launcher.cpu_times()
    cpu = {"launcher": times.user + times.system}
    for name, child in services(pid).items():
        try:
            times = child.cpu_times()
        except psutil.NoSuchProcess:  # it exited meanwhile
            continue
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


VARIANTS = {"full": [], "asr": ["--without", "emotion,gender,voiceid"]}  # voiceid: the baseline has none


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--input", type=Path, help="a sound file instead of synthesised questions")
    parser.add_argument("--array", help="the input's microphone array (pipelines run splitter and ssl too)")
    parser.add_argument("--questions", type=int, default=20, help="how many questions to synthesise (20)")
    parser.add_argument("--grammar", default="robocup", help="robocup (default), a JSGF file, or '' for the LM")
    parser.add_argument("--variants", default="full,asr", help="pipelines to run: full (emotion, gender), "
                        "asr (--without emotion,gender,voiceid); default both")
    parser.add_argument("--port", type=int, default=8123)
    args = parser.parse_args()
    if args.input is None:
        args.input = synthesised_input(args.questions) or REPO / "examples" / "robocup_questions.wav"
    minutes = soundfile.info(str(args.input)).duration / 60
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if set(variants) - set(VARIANTS):
        parser.error(f"--variants takes {', '.join(VARIANTS)}")

    print(f"baseline: playing {args.input} in real time ...", file=sys.stderr, flush=True)
    base_ms, base_texts, base_cpu = baseline(args.input, args.grammar)
    print(f"baseline texts: {base_texts}", file=sys.stderr)
    figures: dict[str, object] = {"audio_s": minutes * 60, "utterances_baseline": len(base_texts),
                                  "baseline_cpu_s_per_min": base_cpu / minutes}
    for kind in ("asr", "full"):
        figures[f"baseline_{kind}_p50_ms"] = percentile(base_ms[kind], 0.5)
        figures[f"baseline_{kind}_p95_ms"] = percentile(base_ms[kind], 0.95)
    for variant in variants:
        print(f"pipeline {variant}: playing {args.input} in real time ...", file=sys.stderr, flush=True)
        extra = VARIANTS[variant] + (["--array", args.array] if args.array else [])
        pipe_ms, pipe_texts, pipe_cpu, startup_cpu, fused = pipeline(args.input, args.grammar,
                                                                     args.port + variants.index(variant), extra)
        print(f"pipeline {variant} texts: {pipe_texts}", file=sys.stderr)
        prefix = f"{variant}_"
        figures[prefix + "utterances"] = len(pipe_ms)
        figures[prefix + "same_texts"] = int(base_texts == pipe_texts)
        figures[prefix + "complete"] = sum(f.get("completion") == "complete" for f in fused)
        for label in ("emotion", "gender"):
            figures[prefix + f"labelled_{label}"] = sum(bool((f.get("aggregates") or {}).get(label)) for f in fused)
        figures[prefix + "pipeline_p50_ms"] = percentile(pipe_ms, 0.5)
        figures[prefix + "pipeline_p95_ms"] = percentile(pipe_ms, 0.95)
        figures[prefix + "pipeline_max_ms"] = max(pipe_ms, default=float("nan"))
        figures[prefix + "overhead_p50_ms"] = percentile(pipe_ms, 0.5) - percentile(base_ms[variant], 0.5)
        figures[prefix + "overhead_p95_ms"] = percentile(pipe_ms, 0.95) - percentile(base_ms[variant], 0.95)
        for name, seconds in sorted(pipe_cpu.items()):
            figures[prefix + f"cpu_s_per_min_{name}"] = seconds / minutes
        figures[prefix + "cpu_s_per_min_total"] = sum(pipe_cpu.values()) / minutes
        for name, seconds in sorted(startup_cpu.items()):
            figures[prefix + f"startup_cpu_s_{name}"] = seconds
    for name, value in figures.items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}")


if __name__ == "__main__":
    main()

"""The framework's CPU per hour of audio against end-of-speech latency, per transport chunk size.

Plays the same speech in real time through ``esiaf run --json --serve --without
emotion,gender,voiceid`` (grabber -> vad -> asr -> orchestrator -> websocket client) once per
chunk size and repeat, interleaved (10, 20, 40, ..., 10, 20, 40, ...), so that the machine's load
falls on every size alike. Per chunk size it reports:

- the framework's CPU (grabber + vad + orchestrator) in CPU-s per hour of audio, as psutil counts
  each process while the audio plays (the median of the repeats); ``net`` subtracts the vad's
  Silero model, measured in this process on the same audio in the same chunks, back to back
  (``model``: onnxruntime's run per 32 ms window, which does not depend on the chunk size; in the
  service, paced, the model runs colder and costs somewhat more, so ``net`` is an upper bound of
  the framework's share). ``--vad energy`` runs the energy segmenter instead (no model at all);
  ``vad_handler_back_to_back``: the vad service's handler alone in this process on the same audio and
  chunks (its model, cutting and segmenting, nothing sent), against which the vad's process shows
  what its transport and its 20-100 wake-ups a second cost;
- each process's CPU-s per hour of audio (the asr's is its recogniser, not the framework's);
- the end-of-speech latency to the fused line, p50 / p95 over every repeat: from the segment's
  end as the vad reported it (bench/latency.py: arrival - (capture time of the utterance's last
  speech sample + the hangover)), and from the true end of the sentence (the synthesiser's truth
  file, questions.json) + the same hangover, which also counts what a bigger chunk adds to the
  vad's decision (the segment's end is a chunk boundary);
- the grabber's audio messages per second.

``--against DIR`` runs another checkout's code (``git worktree add /tmp/base main``) interleaved
with this one's, run by run: a change's saving, measured under the same load. ``--against-env
NAME=VALUE`` sets a variable for those runs only (without ``--against``, this checkout's): a
setting's saving, e.g. ``ESIAF_ORCHESTRATOR_HEARTBEAT_INTERVAL_S=2.5``.

    python -m bench.framework [--chunk-ms 10,20,40,50,100] [--repeats 2] [--questions 8 | --input FILE]
                              [--vad silero|energy] [--against DIR] [--against-env NAME=VALUE]
                              [--profile DIR]

``--vad-in-grabber`` runs this checkout's pipeline with the vad in the grabber's process (``esiaf run
--vad-in-grabber``; not the ``--against`` runs): the grabber's column is then both, and the framework
counts that process once (the vad's column is nan).

``--profile DIR`` samples the grabber, vad and orchestrator with py-spy (``pip install py-spy``,
in the dev extra) while the audio plays, one run per chunk size, writes the collapsed stacks to
DIR/<service>-<chunk>ms.txt and prints each process's top functions (inclusive and own samples;
py-spy leaves out idle threads, but counts a thread woken and waiting for a CPU as busy: under load
most of a paced process's Poller.poll and Socket.send samples are that wait), and before them each
thread's own account from /proc (bench/threads.py): CPU-s per hour, kernel share, time waiting for a
CPU, wake-ups per chunk. ``perf record -e cpu-clock -p PID`` splits the CPU by library (libpython,
libzmq, onnxruntime, the kernel); take it while the audio plays, not across start-up or exit, which
collect garbage. The same by hand, for any process::

    py-spy record --pid PID --rate 250 --nonblocking --format raw -o vad.txt --duration 30
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import soundfile

from bench import threads
from bench.latency import HANGOVER_NS, REPO, percentile, pipeline, synthesised_input
from esiaf import Audio, AudioFormat
from esiaf.speech.silero import SileroModel
from esiaf_services.vad.service import Vad, VadSettings

FRAMEWORK = ("grabber", "vad", "orchestrator")
PROFILED = FRAMEWORK
THREAD_MARGIN_S = 3.0  # the threads' CPU is taken this long before the stream ends: the processes still live
PY_SPY = str(Path(sys.executable).with_name("py-spy"))


def against_truth(path: Path, fused: list[dict]) -> tuple[list[float], int]:
    """Arrival - (the sentence's true end + the hangover) of each fused line, matched to the nearest
    true end, and how many lines give that sentence's words; nothing without a truth file beside
    the input."""
    truth = path.with_suffix(".json")
    if not truth.exists():
        return [], 0
    sentences = json.loads(truth.read_text())["sentences"]
    latencies, right = [], 0
    for line in fused:
        end_ns = line["anchor"]["span"]["end_ns"] - line["stream_start_ns"]
        sentence = min(sentences, key=lambda s: abs(round(s["end_s"] * 1e9) - end_ns))
        latencies.append((line["arrived_ns"] - line["stream_start_ns"] - round(sentence["end_s"] * 1e9)
                          - HANGOVER_NS) / 1e6)
        hypotheses = line["anchor"].get("speech", {}).get("hypotheses", [])
        right += bool(hypotheses) and words(hypotheses[0]["text"]) == words(sentence["text"])
    return latencies, right


def words(text: str) -> list[str]:
    return re.sub(r"[^a-z' ]", " ", text.lower()).split()


def model_cpu_s(path: Path, chunk_ms: float) -> float:
    """CPU-s of the Silero model alone over the file's first channel, fed in ``chunk_ms`` chunks."""
    audio, rate = soundfile.read(str(path), dtype="float32", always_2d=True)
    stream = SileroModel().stream(rate)
    step = max(1, round(rate * chunk_ms / 1000))
    samples = audio[:, 0]
    started = time.process_time()
    for offset in range(0, len(samples), step):
        stream.chunk_probability(samples[offset:offset + step])
    return time.process_time() - started


class QuietVad(Vad):
    """The vad service's class with what it would send dropped: its handler's own cost."""

    def publish(self, *args, **kwargs) -> int:
        return 0

    def emit(self, *args, **kwargs) -> Any:
        return None


def handler_cpu_s(path: Path, chunk_ms: float, vad: str) -> float:
    """CPU-s of the vad service's handler (``Vad.on_audio``: its model, cutting, segmenting, the
    messages it would send built but not sent) over the file's first channel in ``chunk_ms`` chunks,
    back to back in this process: what the vad costs without its transport and its wake-ups."""
    audio, rate = soundfile.read(str(path), dtype="int16", always_2d=True)
    pcm = audio[:, 0].tobytes()
    fmt = AudioFormat(rate, "int16", channels=1)
    service = QuietVad(VadSettings(backend=vad, sample_rate_hz=rate))
    service.setup()
    step = max(1, round(rate * chunk_ms / 1000))
    ns = 1_000_000_000 // rate
    started = time.process_time()
    for sequence, first in enumerate(range(0, len(audio), step), 1):
        last = min(first + step, len(audio))
        service.on_audio(Audio("grabber/audio", "bench", "grabber", sequence, first * ns, last * ns, fmt,
                               pcm[2 * first:2 * last]))
    return time.process_time() - started


class Profiler:
    """py-spy on the framework's processes from the moment the stream starts."""

    def __init__(self, folder: Path, chunk_ms: float, seconds: float):
        self.folder, self.chunk_ms, self.seconds = folder, chunk_ms, seconds
        self.running: list[subprocess.Popen] = []
        # each thread's CPU and wake-ups (bench/threads.py) over the stream's first ``seconds`` less a margin
        self.before: dict[str, tuple[int, dict]] = {}
        self.threads: dict[str, dict[str, threads.Sample]] = {}
        self._timer: threading.Timer | None = None

    def output(self, name: str) -> Path:
        return self.folder / f"{name}-{self.chunk_ms:g}ms.txt"

    def start(self, pids: dict[str, int]) -> None:
        self.before = {name: (pids[name], threads.snapshot(pids[name])) for name in PROFILED if name in pids}
        self._timer = threading.Timer(max(1.0, self.seconds - THREAD_MARGIN_S), self._take_threads)
        self._timer.start()
        for name in PROFILED:
            if name in pids:
                # the orchestrator's own work holds the GIL; without --gil py-spy counts its loop, woken and
                # runnable but not yet on a CPU (a loaded machine), as busy in epoll_wait or a send
                gil = ["--gil"] if name == "orchestrator" else []
                self.running.append(subprocess.Popen(
                    [PY_SPY, "record", "--pid", str(pids[name]), "--rate", "250", *gil, "--nonblocking",
                     "--format", "raw", "-o", str(self.output(name)), "--duration", str(int(self.seconds))],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

    def _take_threads(self) -> None:
        for name, (pid, before) in self.before.items():
            if threads.alive(pid):
                self.threads[name] = threads.difference(before, threads.snapshot(pid), pid)

    def wait(self) -> None:
        for process in self.running:
            process.wait(timeout=self.seconds + 30)
        if self._timer is not None:
            self._timer.join()

    def thread_lines(self, name: str) -> list[str]:
        """Per thread: CPU-s per hour of audio and wake-ups per chunk sent (the grabber's chunks)."""
        if name not in self.threads:
            return []
        seconds = max(1.0, self.seconds - THREAD_MARGIN_S)
        return [f"  threads ({seconds:.0f} s): "
                + threads.describe(self.threads[name], seconds, seconds * 1000 / self.chunk_ms)]


def top_functions(path: Path, count: int = 12) -> list[str]:
    """The functions with the most samples in py-spy's collapsed stacks: inclusive, and own."""
    inclusive: Counter[str] = Counter()
    own: Counter[str] = Counter()
    total = 0
    for line in path.read_text().splitlines():
        stack, _, samples = line.rpartition(" ")
        frames = [f.split(" (", 1)[0] + " (" + Path(f.split(" (", 1)[1].split(":")[0]).name + ")"
                  if " (" in f else f for f in stack.split(";")[1:]]  # [0] is the thread
        n = int(samples)
        total += n
        for frame in set(frames):
            inclusive[frame] += n
        if frames:
            own[frames[-1]] += n
    return [f"{total} samples"] + [f"  {n / total:6.1%} incl  {own[f] / total:6.1%} own  {f}"
                                   for f, n in inclusive.most_common(count)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--chunk-ms", default="10,20,40,50,100", help="chunk sizes, ms (default 10,20,40,50,100)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per chunk size, interleaved (default 2)")
    parser.add_argument("--questions", type=int, default=8, help="how many questions to synthesise (8)")
    parser.add_argument("--input", type=Path, help="a mono sound file instead of synthesised questions")
    parser.add_argument("--vad", choices=("silero", "energy"), default="silero")
    parser.add_argument("--profile", type=Path, metavar="DIR", help="sample grabber, vad and orchestrator with "
                        "py-spy (one run per chunk size, not measured) and print their top functions")
    parser.add_argument("--against", type=Path, metavar="DIR", help="another checkout (e.g. a worktree of main) "
                        "whose code runs interleaved with this one's: before and after a change, in one run")
    parser.add_argument("--against-env", action="append", default=[], metavar="NAME=VALUE",
                        help="an environment variable for the --against runs only (repeatable); without "
                        "--against they run this checkout: e.g. ESIAF_ORCHESTRATOR_HEARTBEAT_INTERVAL_S=2.5")
    parser.add_argument("--port", type=int, default=19300, help="first orchestrator port (one per run)")
    parser.add_argument("--vad-in-grabber", action="store_true",
                        help="this checkout's runs with the vad in the grabber's process (esiaf run --vad-in-grabber)")
    args = parser.parse_args()
    chunks = [float(c) for c in args.chunk_ms.split(",") if c.strip()]
    if args.input is None:
        args.input = synthesised_input(args.questions) or REPO / "examples" / "robocup_questions.wav"
    hours = soundfile.info(str(args.input)).duration / 3600
    extra = ["--without", "emotion,gender,voiceid", "--vad", args.vad]
    port = args.port

    if args.profile:
        if not Path(PY_SPY).exists():  # a dev tool: ./setup.sh does not install it
            raise SystemExit(f"bench/framework.py: --profile needs py-spy beside the interpreter ({PY_SPY}): "
                             ".venv/bin/pip install -e '.[dev]' (or pip install py-spy)")
        args.profile.mkdir(parents=True, exist_ok=True)
        for chunk_ms in chunks:
            profiler = Profiler(args.profile, chunk_ms, hours * 3600)
            print(f"profiling {chunk_ms:g} ms chunks ...", file=sys.stderr, flush=True)
            pipeline(args.input, "robocup", port, [*extra, "--chunk-ms", f"{chunk_ms:g}"], on_start=profiler.start)
            port += 1
            profiler.wait()
            for name in PROFILED:
                if profiler.output(name).exists():
                    print(f"== {name}, {chunk_ms:g} ms chunks:", *profiler.thread_lines(name),
                          *top_functions(profiler.output(name)), sep="\n")
        return

    # one run of each (code, chunk size) per repeat, interleaved
    against_env = dict(item.split("=", 1) for item in args.against_env)
    codes = {"this": REPO, **({"against": (args.against or REPO).resolve()} if args.against or against_env else {})}
    configs = [(code, chunk_ms) for chunk_ms in chunks for code in codes]
    cpu: dict[tuple[str, float], list[dict[str, float]]] = {c: [] for c in configs}
    latency: dict[tuple[str, float], list[float]] = {c: [] for c in configs}
    true_latency: dict[tuple[str, float], list[float]] = {c: [] for c in configs}
    model: dict[tuple[str, float], list[float]] = {c: [] for c in configs}
    texts: dict[tuple[str, float], list[str]] = {c: [] for c in configs}  # per run: right / fused lines
    for repeat in range(args.repeats):
        for config in configs:
            code, chunk_ms = config
            print(f"repeat {repeat + 1}: {chunk_ms:g} ms chunks, {code} ...", file=sys.stderr, flush=True)
            hosted = ["--vad-in-grabber"] if args.vad_in_grabber and code == "this" else []
            ms, said, per_service, _startup, fused = pipeline(args.input, "robocup", port,
                                                               [*extra, "--chunk-ms", f"{chunk_ms:g}", *hosted],
                                                               repo=codes[code],
                                                               env=against_env if code == "against" else None)
            port += 1
            cpu[config].append(per_service)
            latency[config] += ms
            from_true_end, right = against_truth(args.input, fused)
            true_latency[config] += from_true_end
            texts[config].append(f"{right}/{len(said)}")
            model[config].append(model_cpu_s(args.input, chunk_ms) if args.vad == "silero" else 0.0)

    info = soundfile.info(str(args.input))
    against = f", against {codes['against']}" if "against" in codes else ""
    against += f" with {' '.join(args.against_env)}" if args.against_env else ""
    against += ", this with the vad in the grabber's process" if args.vad_in_grabber else ""
    print(f"audio {info.duration:.1f} s, vad {args.vad}, {args.repeats} repeats"
          f"{against}; CPU-s per hour of audio (median of repeats); "
          f"latency over all repeats")
    print("| chunk | code | framework | framework net of model | grabber | vad | vad model | orchestrator | asr "
          "| latency p50 / p95 from segment end | from true end | grabber msg/s | sentences right / lines |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for config in configs:
        code, chunk_ms = config
        def per_hour(name: str, c: tuple[str, float] = config) -> float:
            return statistics.median(run.get(name, float("nan")) for run in cpu[c]) / hours
        framework = statistics.median(sum(run.get(n, 0.0) for n in FRAMEWORK) for run in cpu[config]) / hours
        vad_model = statistics.median(model[config]) / hours
        messages = int(np.ceil(info.frames / max(1, round(info.samplerate * chunk_ms / 1000)))) / info.duration
        utterances = ", ".join(texts[config])
        print(f"| {chunk_ms:g} ms | {code} | {framework:.0f} | {framework - vad_model:.0f} | {per_hour('grabber'):.0f} "
              f"| {per_hour('vad'):.0f} | {vad_model:.0f} | {per_hour('orchestrator'):.0f} | {per_hour('asr'):.0f} "
              f"| {percentile(latency[config], 0.5):.1f} / {percentile(latency[config], 0.95):.1f} ms "
              f"| {percentile(true_latency[config], 0.5):.1f} / {percentile(true_latency[config], 0.95):.1f} ms "
              f"| {messages:.0f} | {utterances} |")
        for name in (*FRAMEWORK, "asr"):
            runs = ", ".join(f"{run.get(name, float('nan')) / hours:.1f}" for run in cpu[config])
            print(f"chunk_{chunk_ms:g}_{code}_cpu_s_per_hour_{name}={runs}")
    for chunk_ms in chunks:  # what the vad's own work costs, without transport or pacing
        print(f"chunk_{chunk_ms:g}_vad_handler_back_to_back_cpu_s_per_hour="
              f"{handler_cpu_s(args.input, chunk_ms, args.vad) / hours:.1f}")
    with open("/proc/loadavg") as handle:
        print("load average:", " ".join(handle.read().split()[:3]))


if __name__ == "__main__":
    main()

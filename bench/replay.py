"""A long ``esiaf run --fast`` replay: memory of every process, what was lost, and how fast it ran.

    python -m bench.replay [--minutes 60] [--repo PATH] [--without emotion,gender,voiceid] [--every 2]

Builds (once, cached in --cache) a mono 16 kHz file of RoboCup questions synthesised with flite,
each followed by 1.5 to 4 s of silence, ``--minutes`` long; plays it with ``esiaf run --fast
--serve --json --grammar robocup`` from the checkout ``--repo`` (default: this one, so that two
checkouts can be measured side by side with one bench); samples the RSS of every process of the
run every ``--every`` seconds (psutil); after the stream's end reads every component's counters
from the orchestrator (audio dropped at the high-water mark, lost on the way, results dropped).

Prints ``name=value`` lines: per service the RSS at the start of the replay, its peak and its end
(MB), the utterances fused beside those played, the drop counts, and the replay speed (audio
seconds per wall second, from the grabber's first chunk to the stream's end). Run it as a module
from the repository root (``python -m bench.replay``).
"""
from __future__ import annotations

import argparse
import datetime
import difflib
import json
import os
import random
import re
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

from esiaf.tools.testing import REPO, free_port, is_spare, normalise

RATE_HZ = 16_000
GAP_S = (1.5, 4.0)  # silence after each question, drawn uniformly
QUIET_S = 30.0  # after the launcher gave up on the stream's end: no result for this long ends the run


def build_file(minutes: float, cache: Path) -> tuple[Path, list[str]]:
    """The replay file and the normalised text of each question in it, in order (cached by length)."""
    sys.path.insert(0, str(REPO / "scripts"))
    from synth_questions import read_questions, synthesise_sentence

    wav, truth_path = cache / f"replay-{minutes:g}min.wav", cache / f"replay-{minutes:g}min.json"
    if wav.exists() and truth_path.exists():
        return wav, json.loads(truth_path.read_text())
    cache.mkdir(parents=True, exist_ok=True)
    table = read_questions(REPO.parent / "shared" / "data" / "robocup" / "questions.tsv")
    voices = {index: synthesise_sentence(text) for index, text in table.items()}
    rng = random.Random(18)
    pieces, texts, frames = [np.zeros(RATE_HZ, dtype="<i2")], [], RATE_HZ
    while frames < minutes * 60 * RATE_HZ:
        index = rng.choice(sorted(voices))
        gap = np.zeros(round(rng.uniform(*GAP_S) * RATE_HZ), dtype="<i2")
        pieces += [voices[index], gap]
        texts.append(normalise(table[index]))
        frames += len(voices[index]) + len(gap)
    soundfile.write(str(wav), np.concatenate(pieces), RATE_HZ, subtype="PCM_16")
    truth_path.write_text(json.dumps(texts))
    return wav, texts


def service_of(process: psutil.Process) -> str | None:
    """``vad`` for a process running ``-m esiaf_services.vad`` (with its instance, if any)."""
    try:
        command = process.cmdline()
        env_instance = process.environ().get("ESIAF_INSTANCE", "")
    except psutil.Error:
        return None
    module = next((c for c in command if c.startswith("esiaf_services.")), None)
    spare = "-spare" if is_spare(process) else ""  # a waiting spare of the service, counted apart
    return None if module is None else (env_instance or module.split(".")[1]) + spare


class Sampler(threading.Thread):
    """RSS (MB) of every service process of the run, every ``every_s`` seconds."""

    def __init__(self, root: psutil.Process, every_s: float):
        super().__init__(daemon=True)
        self.root, self.every_s = root, every_s
        self.samples: list[tuple[float, dict[str, float]]] = []
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(self.every_s if self.samples else 0):
            rss = {}
            for child in self.root.children(recursive=True):
                name = service_of(child)
                if name is not None:
                    try:
                        rss[name] = child.memory_info().rss / 1e6
                    except psutil.Error:
                        continue
            self.samples.append((time.time(), rss))


def components(url: str, token: str) -> list[dict]:
    """Every component of the run, those gone too (the grabber leaves once it has played)."""
    answer = httpx.get(f"{url}/components", params={"include_dead": True}, headers={"Authorization": f"Bearer {token}"},
                       timeout=10)
    return answer.json()["items"]


def fused_texts(lines: list[dict]) -> list[str]:
    """Each fused result's recognised text as it finally stands (latest revision), in order."""
    latest: dict[int, dict[int, str]] = {}
    for line in lines:
        hypotheses = line.get("anchor", {}).get("speech", {}).get("hypotheses") if line.get("type") == \
            "fused_result" else None
        if hypotheses:
            latest.setdefault(line["id"], {})[line["revision"]] = hypotheses[0]["text"]
    return [normalise(by_revision[max(by_revision)]) for by_revision in latest.values()]


def replay(args: argparse.Namespace, wav: Path, truth: list[str]) -> dict[str, float]:
    repo = Path(args.repo).resolve()
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-replay-"))
    port = free_port()
    command = [sys.executable, "-m", "esiaf", "run", "--input", str(wav), "--fast", "--serve", "--json",
               "--grammar", "robocup", "--port", str(port), "--workdir", str(workdir)]
    if args.without:
        command += ["--without", args.without]
    launcher = subprocess.Popen(command, cwd=repo, env={**os.environ, "PYTHONPATH": str(repo)},
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[dict] = []
    marks: dict[str, float] = {}
    ended = threading.Event()

    def read_stdout() -> None:
        assert launcher.stdout is not None
        for line in launcher.stdout:
            if line.startswith("{"):
                lines.append(json.loads(line))
                marks["last_line"] = time.time()
                if lines[-1].get("type") == "stream_end":
                    marks["end"] = time.time()
                    ended.set()

    def read_stderr() -> None:
        assert launcher.stderr is not None
        with (workdir / "launcher.stderr").open("w") as log:
            for line in launcher.stderr:
                log.write(line)
                log.flush()
                if line.startswith("esiaf: playing"):
                    marks["play"] = time.time()
                if line.startswith("esiaf: no end of stream"):  # the launcher gave up waiting (and serves on)
                    marks["gave_up"] = time.time()

    for reader in (read_stdout, read_stderr):
        threading.Thread(target=reader, daemon=True).start()
    sampler = Sampler(psutil.Process(launcher.pid), args.every)
    sampler.start()
    load_before = os.getloadavg()[0]
    try:
        deadline = time.time() + args.timeout
        while not ended.wait(args.every):  # or the launcher gave up on the stream and no result came for QUIET_S
            if "gave_up" in marks and time.time() - marks.get("last_line", 0.0) > QUIET_S:
                marks["end"] = marks.get("last_line", marks["gave_up"])
                break
            if time.time() > deadline:
                raise SystemExit(f"bench/replay: no stream end within {args.timeout:g} s; see {workdir}")
        time.sleep(args.every)  # one more sample after the end
        counts = components(f"http://127.0.0.1:{port}", (workdir / "token").read_text().strip())
    finally:
        sampler.done.set()
        launcher.send_signal(signal.SIGINT)
        try:
            launcher.wait(timeout=30)
        except subprocess.TimeoutExpired:
            launcher.kill()
    # the replay starts when the grabber starts playing (its log says so; the launcher's "playing" line
    # comes as it starts the grabber's process, before its imports)
    grabber_log = (workdir / "logs" / "grabber.log").read_text(errors="replace")
    played = re.search(r"^(\S+ \S+),(\d+) INFO \S+ \[grabber\] playing source=", grabber_log, re.MULTILINE)
    play = marks.get("play", 0.0) if played is None else \
        datetime.datetime.fromisoformat(played[1]).timestamp() + int(played[2]) / 1000
    end = marks["end"]
    during = [(t, rss) for t, rss in sampler.samples if play <= t <= end] or sampler.samples
    result: dict[str, float] = {"audio_s": soundfile.info(str(wav)).duration, "wall_s": end - play,
                                "load_avg_1min_before": load_before, "load_avg_1min_after": os.getloadavg()[0]}
    result["speed_x_realtime"] = result["audio_s"] / result["wall_s"]
    result["stream_ended"] = int(ended.is_set())  # 0: it never ended; wall_s then runs to the last result
    for name in sorted({n for _, rss in sampler.samples for n in rss}):
        series = [rss[name] for _, rss in during if name in rss]
        if series:
            result[f"rss_mb_{name}_start"], result[f"rss_mb_{name}_peak"] = series[0], max(series)
            result[f"rss_mb_{name}_end"] = series[-1]
    heard = fused_texts(lines)
    matcher = difflib.SequenceMatcher(a=truth, b=heard, autojunk=False)
    result.update(utterances_played=len(truth), utterances_fused=len(heard),
                  utterances_matched=sum(block.size for block in matcher.get_matching_blocks()))
    for component in counts:
        stats = component.get("stats") or {}
        name = component.get("instance") or component["name"]
        dropped = sum(o.get("dropped", 0) for o in stats.get("outputs", {}).values())
        lost = sum(i.get("lost", 0) for i in stats.get("inputs", {}).values())
        result[f"dropped_audio_{name}"], result[f"lost_audio_{name}"] = dropped, lost
        result[f"dropped_results_{name}"] = stats.get("results_dropped", 0)
    # the grabber has left by now (it leaves once it has played): what it dropped is in its log
    result["dropped_audio_grabber"] = grabber_log.count("audio dropped at high-water mark")
    print(f"bench/replay: logs in {workdir}", file=sys.stderr)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="length of the replayed file (default 60)")
    parser.add_argument("--repo", default=str(REPO), help="the checkout whose esiaf runs the pipeline (default: this)")
    parser.add_argument("--without", default="emotion,gender,voiceid", help="analysers left out (esiaf run --without)")
    parser.add_argument("--every", type=float, default=2.0, help="seconds between RSS samples (default 2)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    parser.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "esiaf-bench-replay"),
                        help="where the built file is kept")
    args = parser.parse_args()
    wav, truth = build_file(args.minutes, Path(args.cache))
    print(f"bench/replay: {wav} ({len(truth)} questions), esiaf from {args.repo}", file=sys.stderr, flush=True)
    for name, value in replay(args, wav, truth).items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}", flush=True)


if __name__ == "__main__":
    main()

"""How soon a robot knows something of what is being said: partial results against speech onsets.

    python -m bench.partials [--asr pocketsphinx|whisper] [--runs 1] [--denoiser auto|on|off]

Plays ``examples/robocup_questions.wav`` in real time through ``esiaf run --json --partials`` (the
recogniser alone: ``--without emotion,gender,voiceid``) and measures, per question, on the capture
clock (real time: capture time is the wall clock the orchestrator stamps ``received_ns`` with):

- speech start → first partial with words: the truth file's start of speech to the first ``partial``
  event received with a text;
- speech start → first stable word: ... to the first partial with a ``stable`` prefix;
- speech end → fused result: the truth file's end of speech to the fused result's ``published_ns``;
- segment end → fused result: the end of the asr result's span (the vad's segment, closed after its
  hang-over) to the same.

The stream's first question has no partials with pocketsphinx (decoded whole, for its cepstral
mean), so it is left out of the first two; its row says so.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if __name__ == "__main__":
    sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402

from esiaf.tools.testing import free_port  # noqa: E402

EXAMPLE = REPO / "examples" / "robocup_questions.wav"
TRUTH = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"]


def run_once(asr: str, options: list[str], port: int = 0, env: list[str] | None = None) -> list[dict]:
    """The JSON lines of one real-time run (``port``: the orchestrator's; 0: a free one)."""
    with tempfile.TemporaryDirectory(prefix="esiaf-partials-") as work:
        args = [sys.executable, "-m", "esiaf", "run", "--input", str(EXAMPLE), "--grammar", "robocup", "--json",
                "--partials", "--without", "emotion,gender,voiceid", "--port", str(port or free_port()),
                "--workdir", work, *options]
        if asr != "pocketsphinx":
            args += ["--asr", asr]
        extra = dict(item.split("=", 1) for item in env or [])
        done = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=300,
                              env={**os.environ, **extra})
        if done.returncode != 0:
            raise SystemExit(f"esiaf run failed ({done.returncode}): {done.stderr[-2000:]}")
        return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def measure(lines: list[dict]) -> dict[str, list[float]]:
    start = next(line["start_ns"] for line in lines if line["type"] == "stream_start")
    onsets = [start + round(s["start_s"] * 1e9) for s in TRUTH]
    ends = [start + round(s["end_s"] * 1e9) for s in TRUTH]
    figures: dict[str, list[float]] = {"first_words_ms": [], "first_stable_ms": [], "end_to_fused_ms": [],
                                       "segment_to_fused_ms": []}
    for i, (onset, end) in enumerate(zip(onsets, ends, strict=True)):
        following = onsets[i + 1] if i + 1 < len(onsets) else float("inf")
        partials = [p for p in lines if p["type"] == "partial" and not p["closed"]
                    and onset - 1e9 <= p["received_ns"] < following]
        worded = [p["received_ns"] for p in partials if p["text"]]
        stable = [p["received_ns"] for p in partials if p["stable"]]
        if worded:
            figures["first_words_ms"].append((min(worded) - onset) / 1e6)
        if stable:
            figures["first_stable_ms"].append((min(stable) - onset) / 1e6)
        fused = [f for f in lines if f["type"] == "fused_result" and f["revision"] == 1
                 and onset - 1e9 <= f["anchor"]["span"]["start_ns"] < following]
        if fused:
            figures["end_to_fused_ms"].append((fused[0]["published_ns"] - end) / 1e6)
            segment_end = fused[0]["anchor"]["span"]["end_ns"]
            figures["segment_to_fused_ms"].append((fused[0]["published_ns"] - segment_end) / 1e6)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--asr", default="pocketsphinx", choices=["pocketsphinx", "whisper"])
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--denoiser", default="auto", choices=["auto", "on", "off"], help="esiaf run's option")
    parser.add_argument("--port", type=int, default=0, help="the orchestrator's port (default: a free one)")
    parser.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                        help="an environment variable for esiaf run (e.g. ESIAF_ASR_WHISPER__BEAM_SIZE=3); repeatable")
    args = parser.parse_args()
    totals: dict[str, list[float]] = {}
    for _ in range(args.runs):
        for name, values in measure(run_once(args.asr, ["--denoiser", args.denoiser], args.port, args.env)).items():
            totals.setdefault(name, []).extend(values)
    print(f"asr={args.asr} denoiser={args.denoiser} runs={args.runs} questions={len(TRUTH)} per run")
    for name, values in totals.items():
        if values:
            ordered = sorted(values)
            p95 = ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]
            print(f"{name:18s} n={len(values):3d} p50={statistics.median(values):7.0f} ms p95={p95:7.0f} ms "
                  f"min={ordered[0]:6.0f} max={ordered[-1]:6.0f}")
        else:
            print(f"{name:18s} n=  0")


if __name__ == "__main__":
    main()

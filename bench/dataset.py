"""The thesis' first experiment (its Fig. 5.7), reproduced: a data-set-sized run through the realistic
pipeline and through an in-process monolith running the same models, beside the thesis' table.

The data set (bench/corpus.py): ``--minutes`` of EmoDB utterances (emotion and gender labels) and
flite-spoken RoboCup questions (text and gender), 2.5-3.5 s apart, each rendered for the array
(``--array``, default respeaker4: 4 channels) from a known direction; cached between runs.

- **pipeline**: ``esiaf run --input FILE --array ARRAY --grammar robocup --json --serve [--fast]``
  with its default analysers (vad silero; splitter, ssl, beamformer; asr; emotion with gender as a
  guest; voiceid), as a user runs it. CPU-s per process (psutil) while the audio plays. Latency per
  service from the orchestrator's database (``results``): a result's arrival minus the arrival of
  the VAD's result for the same segment, i.e. from the moment the VAD closed the segment (the
  same in real time and ``--fast``; for ssl, its last frame overlapping the segment); ``fused``
  is the first publication of the fused result. In real time ``vad`` is the VAD's own latency
  after the end of speech (capture time; its 400 ms of silence included), and ``end_of_speech``
  that of the fused result.
- **monolith** (bench/monolith.py): the same SSL and beamformer components, VAD (silero),
  recogniser and grammar, emotion and gender models (features computed once) and voiceid encoder
  in one loop in a child process. Its stages run one after the other, so a stage's latency
  includes those before it; CPU-s per stage.

Scoring, per utterance against the fused result (monolith: segment) overlapping it most: lost
(none overlaps), spurious results (overlapping no utterance), text right (questions), direction
error (mean, and within 15°), emotion (EmoDB) and gender accuracy.

    python -m bench.dataset [--minutes 30] [--modes fast,realtime] [--parts pipeline,monolith]
                            [--together] [--port 19200] [--seed 1] [--array respeaker4]

``--together`` runs the monolith at the same time as the pipeline (real time only: both paced by the
clock). It prints a table, then ``name=value`` lines (``<part>_<mode>_<figure>``).
"""
from __future__ import annotations

import argparse
import bisect
import json
import math
import os
import sqlite3
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import httpx

from bench.corpus import build
from bench.latency import REPO, percentile, pipeline
from bench.monolith import MonolithRun, replay
from esiaf.tools.robocup_scoring import angle_difference_deg, normalise

# Fig. 5.7 of the thesis: 2 h 49 min (169 min) of audio on an i7-7500U; latency from segment end to result
THESIS = {"monolith (vad, asr)": ("0.063", "", 229), "pipeline (grabber, vad, asr, orch.)": ("1.014", "", 1209),
          "realistic (+ emotion, gender)": ("", "1.780", 37517)}
THESIS_MIN = 169.0
WITHIN_DEG = 15.0
SEGMENT_SERVICES = ("asr", "emotion", "gender", "voiceid")


def monolith_figures(run: MonolithRun, fast: bool) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Per stage CPU and latencies, and the utterances as the scoring takes them."""
    figures: dict[str, Any] = {"wall_s": run.wall_s, "replay_s": run.wall_s}
    for stage, seconds in run.cpu_s.items():
        figures[f"cpu_s_{stage}"] = seconds
    for stage in ("asr", "emotion", "gender", "voiceid", "ssl", "all"):
        latencies = [u.latency_ms(stage) for u in run.utterances if stage in u.done_ns]
        figures[f"{stage}_p50_ms"], figures[f"{stage}_p95_ms"] = percentile(latencies, .5), percentile(latencies, .95)
    if not fast:
        vad = [(u.closed_ns - u.end_ns) / 1e6 for u in run.utterances]
        figures["vad_p50_ms"], figures["vad_p95_ms"] = percentile(vad, .5), percentile(vad, .95)
    results = [{"start_s": (u.start_ns - run.origin_ns) / 1e9, "end_s": (u.end_ns - run.origin_ns) / 1e9,
                "text": u.text, "azimuth_deg": u.azimuth_deg, "emotion": u.labels.get("emotion"),
                "gender": u.labels.get("gender"), "completion": "complete"} for u in run.utterances]
    return figures, results


def service_latencies(db: Path, fast: bool) -> dict[str, list[float]]:
    """ms per service from the VAD's result of each segment (see the module's docstring)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT component, start_ns, end_ns, received_ns FROM results ORDER BY end_ns").fetchall()
        fused = con.execute("SELECT start_ns, end_ns, MIN(published_ns) FROM fused GROUP BY id").fetchall()
    finally:
        con.close()
    vad = {(s, e): r for c, s, e, r in rows if c == "vad"}
    out: dict[str, list[float]] = {name: [] for name in (*SEGMENT_SERVICES, "ssl", "fused")}
    for component, start, end, received in rows:
        if component in SEGMENT_SERVICES and (start, end) in vad:
            out[component].append((received - vad[start, end]) / 1e6)
    ssl = [(e, s, r) for c, s, e, r in rows if c == "ssl"]
    ssl_ends = [e for e, _, _ in ssl]
    for (start, end), closed in vad.items():
        i = bisect.bisect_left(ssl_ends, end)  # the first frame ending at or after the segment's end
        frame = ssl[i] if i < len(ssl) and ssl[i][1] < end else ssl[i - 1] if i and ssl[i - 1][0] > start else None
        if frame is not None:
            out["ssl"].append((frame[2] - closed) / 1e6)
    for start, end, published in fused:
        if (start, end) in vad:
            out["fused"].append((published - vad[start, end]) / 1e6)
    if not fast:
        out["vad"] = [(r - e) / 1e6 for (_, e), r in vad.items()]
        out["end_of_speech"] = [(p - e) / 1e6 for _, e, p in fused]
    return out


def fused_results(db: Path) -> list[dict[str, Any]]:
    """The latest revision of each fused result, as the scoring takes it (seconds from the stream's start)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        origin, = con.execute("SELECT MIN(start_ns) FROM streams").fetchone()
        rows = con.execute("SELECT f.json FROM fused f JOIN (SELECT id, MAX(revision) r FROM fused GROUP BY id) l "
                           "ON f.id = l.id AND f.revision = l.r ORDER BY f.start_ns").fetchall()
    finally:
        con.close()
    results = []
    for (text,) in rows:
        message = json.loads(text)
        span, aggregates = message["anchor"]["span"], message.get("aggregates") or {}
        hypotheses = (message["anchor"].get("speech") or {}).get("hypotheses") or []
        results.append({"start_s": (span["start_ns"] - origin) / 1e9, "end_s": (span["end_ns"] - origin) / 1e9,
                        "text": hypotheses[0]["text"] if hypotheses and not hypotheses[0].get("out_of_set") else "",
                        "azimuth_deg": (aggregates.get("ssl") or {}).get("azimuth_deg"),
                        "emotion": (aggregates.get("emotion") or {}).get("label"),
                        "gender": (aggregates.get("gender") or {}).get("label"),
                        "completion": message.get("completion"), "revision": message.get("revision", 1)})
    return results


def score(truth: list[dict[str, Any]], results: list[dict[str, Any]]) -> dict[str, Any]:
    """Each utterance against the result overlapping it most."""
    starts = [r["start_s"] for r in results]
    used: set[int] = set()
    lost = text_right = questions = emotion_right = emotions = gender_right = genders = 0
    errors: list[float] = []
    for utterance in truth:
        lo = max(0, bisect.bisect_left(starts, utterance["start_s"] - 10.0))
        hi = bisect.bisect_right(starts, utterance["end_s"])
        overlaps = [(min(utterance["end_s"], results[i]["end_s"]) - max(utterance["start_s"], results[i]["start_s"]), i)
                    for i in range(lo, hi)]
        used.update(i for o, i in overlaps if o > 0)
        best = max((o for o in overlaps if o[0] > 0), default=None)
        if best is None:
            lost += 1
            continue
        result = results[best[1]]
        if utterance["kind"] == "robocup":
            questions += 1
            text_right += normalise(result["text"]) == normalise(utterance["text"])
        if utterance["emotion"]:
            emotions += 1
            emotion_right += result["emotion"] == utterance["emotion"]
        genders += 1
        gender_right += result["gender"] == utterance["gender"]
        if result["azimuth_deg"] is not None:
            errors.append(angle_difference_deg(result["azimuth_deg"], utterance["azimuth_deg"]))
    completion = [r["completion"] for r in results]
    return {"utterances": len(truth), "results": len(results), "lost": lost, "spurious": len(results) - len(used),
            "complete": completion.count("complete"), "not_complete": len(completion) - completion.count("complete"),
            "revised": sum(r.get("revision", 1) > 1 for r in results),
            "text_right": text_right / questions if questions else math.nan,
            "direction_error_deg": sum(errors) / len(errors) if errors else math.nan,
            "direction_within_15": sum(e <= WITHIN_DEG for e in errors) / len(errors) if errors else math.nan,
            "emotion_right": emotion_right / emotions if emotions else math.nan,
            "gender_right": gender_right / genders if genders else math.nan}


def counters(value: Any, path: str = "") -> dict[str, float]:
    """Numeric leaves of the orchestrator's answers that count losses (dropped, lost, refused, gaps, timed out)."""
    found: dict[str, float] = {}
    if isinstance(value, dict):
        for key, item in value.items():
            found.update(counters(item, f"{path}.{key}" if path else str(key)))
    elif isinstance(value, list):
        for item in value:
            name = (item.get("name") or item.get("id")) if isinstance(item, dict) else ""
            found.update(counters(item, f"{path}[{name}]"))
    elif isinstance(value, int | float) and not isinstance(value, bool) and value and any(
            word in path.rsplit(".", 1)[-1] for word in ("drop", "lost", "refused", "gap", "timed_out", "timeout_")):
        found[path] = value
    return found


def run_pipeline(audio: Path, grammar: str, fast: bool, array: str, port: int) -> tuple[dict[str, Any], list]:
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-dataset-run-"))
    stats: dict[str, Any] = {}

    def ask() -> None:
        token = (workdir / "token").read_text().strip()
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {token}"},
                          timeout=10) as client:
            for path in ("/fusions/stats", "/components"):
                stats[path] = client.get(path).json()

    extra = ["--array", array] + (["--fast"] if fast else [])
    started = time.monotonic()
    _, _, cpu, startup, _ = pipeline(audio, grammar, port, extra, workdir=workdir, on_ended=ask, progress_s=30)
    con = sqlite3.connect(f"file:{workdir / 'esiaf.db'}?mode=ro", uri=True)
    try:  # from the stream's announcement to its last fused result: start-up and shut-down left out
        announced, last = con.execute("SELECT (SELECT MIN(announced_ns) FROM streams), MAX(published_ns) FROM fused"
                                      ).fetchone()
    finally:
        con.close()
    figures: dict[str, Any] = {"wall_s": time.monotonic() - started, "replay_s": (last - announced) / 1e9,
                               "workdir": str(workdir)}
    for name, seconds in sorted(cpu.items()):
        figures[f"cpu_s_{name}"] = seconds
    for name, values in service_latencies(workdir / "esiaf.db", fast).items():
        figures[f"{name}_p50_ms"], figures[f"{name}_p95_ms"] = percentile(values, .5), percentile(values, .95)
        figures[f"{name}_count"] = len(values)
    for name, value in (stats.get("/fusions/stats") or {}).get("counters", {}).items():
        figures[f"fusions_{name}"] = value
    for name, value in counters(stats).items():
        figures[f"counter[{name}]"] = value
    figures["startup_cpu_s"] = sum(startup.values())
    return figures, fused_results(workdir / "esiaf.db")


def table(rows: dict[str, dict[str, Any]], minutes: float) -> str:
    """Thesis beside each run: latency (after the segment's end) of the recogniser and of all, CPU."""
    lines = [f"{'run':50} {'speed x':>8} {'asr p50/p95 s':>14} {'all p50/p95 s':>14} {'CPU-s':>8} {'CPU-s/min':>9}"]
    for name, (asr, last, cpu) in THESIS.items():
        lines.append(f"{'thesis 2019: ' + name:50} {1.0:8.1f} {asr:>14} {last:>14} {cpu:8.0f} {cpu / THESIS_MIN:9.2f}")
    for name, f in rows.items():
        total = sum(v for k, v in f.items() if k.startswith("cpu_s_"))
        last = "all" if name.startswith("monolith") else "fused"
        lines.append(f"{name:50} {minutes * 60 / f['replay_s']:8.1f} "
                     f"{f['asr_p50_ms'] / 1e3:6.3f}/{f['asr_p95_ms'] / 1e3:<7.3f} "
                     f"{f[last + '_p50_ms'] / 1e3:6.3f}/{f[last + '_p95_ms'] / 1e3:<7.3f} {total:8.1f} "
                     f"{total / minutes:9.2f}")
    lines.append("")
    lines.append(f"{'run':24} {'service':12} {'CPU-s':>8} {'CPU-s/min':>9} {'p50 ms':>8} {'p95 ms':>8}")
    for name, f in rows.items():
        services = sorted({k[6:] for k in f if k.startswith("cpu_s_")} | {k[:-7] for k in f if k.endswith("_p50_ms")})
        for service in services:
            seconds = f.get(f"cpu_s_{service}")
            lines.append(f"{name:24} {service:12} {'' if seconds is None else f'{seconds:8.1f}':>8} "
                         f"{'' if seconds is None else f'{seconds / minutes:9.2f}':>9} "
                         f"{f.get(service + '_p50_ms', math.nan):8.1f} {f.get(service + '_p95_ms', math.nan):8.1f}")
    lines.append("")
    keys = ("utterances", "results", "lost", "spurious", "complete", "not_complete", "revised", "text_right",
            "direction_error_deg", "direction_within_15", "emotion_right", "gender_right")
    lines.append(f"{'run':24} " + " ".join(f"{k[:11]:>11}" for k in keys))
    for name, f in rows.items():
        lines.append(f"{name:24} " + " ".join(f"{f[k]:11.3f}" if isinstance(f[k], float) else f"{f[k]:11}"
                                              for k in keys))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="length of the data set (default 30)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--array", default="respeaker4")
    parser.add_argument("--grammar", default="robocup", help="robocup (default), a JSGF file, or '' for the LM")
    parser.add_argument("--modes", default="fast", help="fast, realtime or both (fast,realtime); default fast")
    parser.add_argument("--parts", default="pipeline,monolith", help="pipeline, monolith or both (default)")
    parser.add_argument("--together", action="store_true", help="real time: the monolith beside the pipeline")
    parser.add_argument("--port", type=int, default=19200)
    parser.add_argument("--cache", type=Path, help="where rendered data sets are kept (default $TMPDIR/esiaf-dataset)")
    args = parser.parse_args()
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if set(modes) - {"fast", "realtime"} or set(parts) - {"pipeline", "monolith"}:
        parser.error("--modes takes fast,realtime and --parts pipeline,monolith")
    audio, truth = build(args.minutes, args.seed, args.array, args.cache)
    print(f"dataset: {len(truth['utterances'])} utterances, {truth['speech_s'] / 60:.1f} min of speech in "
          f"{args.minutes:g} min; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}",
          file=sys.stderr, flush=True)
    rows: dict[str, dict[str, Any]] = {}
    with ProcessPoolExecutor(1) as pool:  # the monolith in a process of its own: its CPU is its own
        for mode in modes:
            fast = mode == "fast"
            job = None
            if "monolith" in parts:
                print(f"monolith {mode}: playing {audio} ...", file=sys.stderr, flush=True)
                job = pool.submit(replay, audio, args.grammar, fast, args.array)
                if not (args.together and not fast and "pipeline" in parts):
                    job.result()
            if "pipeline" in parts:
                print(f"pipeline {mode}: playing {audio} ...", file=sys.stderr, flush=True)
                figures, results = run_pipeline(audio, args.grammar, fast, args.array, args.port)
                rows[f"pipeline_{mode}"] = {**figures, **score(truth["utterances"], results)}
            if job is not None:
                figures, results = monolith_figures(job.result(), fast)
                rows[f"monolith_{mode}"] = {**figures, **score(truth["utterances"], results)}
    print(f"dataset: {args.minutes:g} min, {len(truth['utterances'])} utterances, array {args.array}, "
          f"grammar {args.grammar or 'LM'}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; {os.cpu_count()} CPUs; repo {REPO}")
    print(table(rows, args.minutes))
    for name, f in rows.items():
        for key, value in f.items():
            print(f"{name}_{key}={value:.3f}" if isinstance(value, float) else f"{name}_{key}={value}")


if __name__ == "__main__":
    main()

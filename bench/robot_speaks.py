"""The robot hears itself: every target of the echo path measured in one run, side by side.

Three parts, each at the issue's conditions (the person 10 dB below the robot's echo at the
microphones, babble 10 dB below the person):

- **the canceller alone** (``bench/aec.py``'s scene and figures, its default start, with ``--slow-start`` the
  one before beside it; one array, ``--conditions``
  DELAY_MS:PPM pairs spanning 0-300 ms and ±100 ppm, neither told to the canceller): ``erle_db`` from
  1 s after the robot first speaks (energy-weighted over its speech to the pause), ``erle_median_db``
  (the median of its per-second values there), ``erle_converged_db`` from 1 s after the delay tracker's
  first estimate (when the canceller can start to converge), and ``cpu_pct`` (process time of the
  canceller and its alignment per second of 4-channel audio, in % of one core);
- **through the pipeline, the robot answering each question** (``esiaf eval robocup`` rooms, ``--runs``
  rooms, rendered once without and once with the robot's loudspeaker, ``--robot-speaks``): of the
  questions the robot's voice overlaps (its echo in the question's span), those recognised with the
  robot speaking against the same questions' rate without it (target: >= 80 %), and their directions
  within 15° (target: >= 85 %);
- **the robot talking for ``--talk-s`` seconds alone** (flite answers with short pauses, the same
  loudspeaker 7 cm from the array, babble 20 dB below the echo, a room of the harness) through
  ``esiaf run --fast --playback --include-robot``: the fused results not tagged ``source: robot``
  (each is the robot's own speech taken for a user; target 0) and those tagged.

    nice -n 10 python -m bench.robot_speaks [--array respeaker4] [--conditions 0:100,150:-100,300:100,300:-100]
        [--runs 2] [--talk-s 300] [--port 23200] [--workdir DIR] [--json out.json] [--skip aec,eval,talk]
        [--slow-start] [--gate-before] [--babble-alone]
        [-- ESIAF RUN OPTIONS]

``--babble-alone`` runs the talk a second time on its microphones without the robot's echo (the scene less
the echo rendered alone: its babble at the same scale), the player playing as before: the fused user
utterances the babble alone makes (names ending ``_babble_alone``).

``--gate-before`` runs the robot's half of the eval part and the talk part a second time with the delay
tracker's gate as it was before 2026-11-28 (``ESIAF_AEC_DELAY_OUTLIER_MS=20``: an estimate up to 20 ms off
the line taken into it), its figures beside the default's (names ending ``_gate_before``).

Ends with a table of the targets and ``name=value`` lines.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

FS = 16000
PERSON_BELOW_ECHO_DB = 10.0
BABBLE_BELOW_PERSON_DB = 10.0
GATE_BEFORE = {"ESIAF_AEC_DELAY_OUTLIER_MS": "20"}  # the delay tracker's gate before 2026-11-28
BABBLE_ALONE = "_babble_alone"  # the talk's control: its babble without the robot's echo


@contextlib.contextmanager
def environment(values: dict[str, str]):
    """``values`` in the environment of the pipelines started meanwhile."""
    before = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def canceller_part(array: str, conditions: list[tuple[float, float]], seconds: float, seed: int,
                   backend: str, slow_start: bool = False) -> list[dict]:
    from bench import aec
    recogniser = aec.Recogniser()
    rows = []
    variants = [("", aec.FAST_START), *([("slow-start", aec.SLOW_START)] if slow_start else [])]
    for delay_ms, ppm in conditions:
        scene = aec.render(array, seconds, delay_ms, ppm, seed)
        for variant, options in variants:
            figures = aec.measure(scene, array, backend, delay_ms, ppm, recogniser, options=options)
            row = asdict(figures)
            row["variant"] = variant
            row["erle_converged_db"] = converged_erle(scene, backend, options)
            rows.append(row)
            print_row(array, backend, variant, row)
    return rows


def print_row(array: str, backend: str, variant: str, row: dict) -> None:
    delay_ms, ppm = row["delay_ms"], row["ppm"]
    name = f"{backend} {variant}" if variant else backend
    print(f"aec {array} {name} delay {delay_ms:.0f} ms drift {ppm:+.0f} ppm: ERLE {row['erle_db']:.1f} dB "
          f"(median {row['erle_median_db']:.1f}, 1 s after the delay is known {row['erle_converged_db']:.1f}, "
          f"restart {row['erle_restart_db']:.1f}); double talk {row['recognised']}/{row['asked']} "
          f"(no robot {row['recognised_clean']}); CPU {row['cpu_pct']:.2f} %; delay est "
          f"{row['delay_estimated_ms']:.1f} ms, drift est {row['drift_estimated_ppm']:+.0f} ppm", flush=True)


def converged_erle(scene, backend: str, options: dict | None = None) -> float:
    """ERLE over the robot's first stretch of speech from 1 s after the delay tracker's first estimate."""
    from bench import aec
    echo_only = scene.echo + scene.noise
    out, _, stream = aec.cancel(backend, echo_only, scene.reference, True, options)
    known = getattr(stream.tracker, "first_known_s", None)  # type: ignore[attr-defined]
    first_known = math.nan if known is None else known
    start, end = scene.robot_spans[0]
    if math.isnan(first_known) or first_known + 1.0 >= end:
        return math.nan
    return aec.erle_db(echo_only, out, max(start, first_known) + 1.0, end)


def overlapped(run_dir: Path, start_s: float, end_s: float) -> bool:
    """The robot's echo is in the question's span (its reference, 100 ms late, above 2 % of its peak)."""
    import soundfile

    from esiaf.tools.evaluation import ROBOT_DELAY_S
    reference = soundfile.read(str(run_dir / "robot.wav"))[0]
    first, last = int((start_s - ROBOT_DELAY_S) * FS), int((end_s - ROBOT_DELAY_S) * FS)
    part = np.abs(reference[max(first, 0):max(last, 0)])
    return bool(len(part)) and bool(np.mean(part > 0.02 * np.max(np.abs(reference))) > 0.1)


def eval_part(array: str, runs: int, seed: int, work: Path, port: int, options: list[str],
              variants: dict[str, dict[str, str]]) -> dict[str, dict]:
    """The harness's rooms without the robot once, and with it once per variant (its environment)."""
    from esiaf.tools import evaluation
    scored = {}
    for name, env in {"silent": {}, **{f"robot{v}": e for v, e in variants.items()}}.items():
        argv = ["robocup", "--runs", str(runs), "--array", array, "--seed", str(seed), "--no-oracle",
                "--port", str(port), "--workdir", str(work / name.replace("_", "-"))]
        args, _ = evaluation.parse_args([*argv, *(["--robot-speaks"] if name != "silent" else [])])
        evaluation.check(args)
        with environment(env):
            scored[name] = evaluation.evaluate(args, options)
    return {variant: eval_figures(array, scored["silent"], scored[f"robot{variant}"],
                                  work / f"robot{variant}".replace("_", "-"), variant) for variant in variants}


def eval_figures(array: str, silent: list, robot: list, robot_dir: Path, variant: str) -> dict:
    from esiaf.tools.robocup_scoring import direction_right
    scored = {False: silent, True: robot}
    both, clean_right, robot_right, directions = 0, 0, 0, 0
    all_robot = [q for run in scored[True] for q in run.questions]
    for silent_run, robot_run in zip(scored[False], scored[True], strict=True):
        for silent_q, robot_q in zip(silent_run.questions, robot_run.questions, strict=True):
            if not overlapped(robot_dir / robot_run.name, robot_q.start_s, robot_q.end_s):
                continue
            both += 1
            clean_right += silent_q.recognised
            robot_right += robot_q.recognised
            directions += direction_right(robot_q)
    figures = {
        "questions": len(all_robot),
        "overlapped": both,
        "overlapped_recognised_silent": clean_right,
        "overlapped_recognised_robot": robot_right,
        "double_talk_ratio": robot_right / clean_right if clean_right else math.nan,
        "overlapped_directions_within_15": directions / both if both else math.nan,
        "recognised_silent": sum(q.recognised for run in scored[False] for q in run.questions),
        "recognised_robot": sum(q.recognised for q in all_robot),
        "directions_silent": sum(direction_right(q) for run in scored[False] for q in run.questions),
        "directions_robot": sum(direction_right(q) for q in all_robot),
        "spurious_silent": sum(run.spurious for run in scored[False]),
        "spurious_robot": sum(run.spurious for run in scored[True]),
    }
    name = f"{array} {variant.strip('_')}" if variant else array
    print(f"eval {name}, {len(robot)} room(s): questions the robot's voice overlaps {both}/{len(all_robot)}: "
          f"recognised {robot_right} with the robot speaking, {clean_right} without "
          f"({100 * figures['double_talk_ratio']:.0f} %), directions within 15° {directions}/{both}; all questions: "
          f"recognised {figures['recognised_robot']} (silent robot {figures['recognised_silent']}), directions "
          f"{figures['directions_robot']} ({figures['directions_silent']}), spurious {figures['spurious_robot']} "
          f"({figures['spurious_silent']})", flush=True)
    return figures


def talk_part(array: str, seconds: float, seed: int, work: Path, port: int, options: list[str],
              variants: dict[str, dict[str, str]], babble_alone: bool = False) -> dict[str, dict]:
    """The robot talking alone for ``seconds``: fused results through the pipeline, robot-tagged or not, once
    per variant (its environment added to the pipeline's); with ``babble_alone`` once more on the same
    microphones without the robot's echo (the player playing as before)."""
    import soundfile

    from bench.aec import flite, questions_and_answers
    from esiaf.scenes import NoiseSource, Scene, SpeechSource, render
    from esiaf.tools import evaluation
    work.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 7])
    answers = [f"The answer to your question is: {a}. Do you have another question for me?"
               for _, a in questions_and_answers()]
    track, at, transcript = np.zeros(int(seconds * FS)), int(0.5 * FS), []
    while at < len(track) - FS:
        text = str(rng.choice(answers))
        clip = flite(text, "kal16")[:len(track) - at]
        track[at:at + len(clip)] = clip
        transcript.append({"start_s": at / FS, "text": text})
        at += len(clip) + int(rng.uniform(0.3, 1.5) * FS)
    reference = work / "robot.wav"
    soundfile.write(str(reference), (0.5 * track / np.max(np.abs(track))).astype(np.float32), FS)
    (work / "robot.json").write_text(json.dumps(transcript))
    delay = round(evaluation.ROBOT_DELAY_S * FS)
    echo = work / "robot-echo.wav"
    soundfile.write(str(echo), np.concatenate([np.zeros(delay), track])[:len(track)].astype(np.float32), FS)
    babble = work / "babble.wav"
    if not babble.exists():
        evaluation.babble_clip(np.random.default_rng([seed, 8]), [a for _, a in questions_and_answers()], babble)
    # the robot's echo is the scene's "speech" (a scene needs one); the babble 20 dB below it
    room = (7.5, 7.0, 3.0)
    scene = Scene(array=array, room_m=room, rt60_s=0.45, array_position_m=(3.7, 3.4, 1.2), array_heading_deg=30.0,
                  speech=[SpeechSource(clip=str(echo), text="(the robot)", azimuth_deg=0.0, distance_m=0.07,
                                       elevation_deg=-45.0)],
                  noise=[NoiseSource(clip=str(babble), azimuth_deg=20.0, distance_m=2.5,
                                     snr_db=PERSON_BELOW_ECHO_DB + BABBLE_BELOW_PERSON_DB)],
                  tail_s=1.0, seed=seed)
    signals, _ = render(scene)
    audio = work / "scene.flac"
    pcm = np.round(signals * 32767).astype(np.int16)
    soundfile.write(str(audio), pcm, FS)
    robot_speech_s = float(np.sum(np.abs(track) > 0) / FS)
    runs = {variant: (audio, env) for variant, env in variants.items()}
    if babble_alone:  # the scene less its echo rendered alone (the babble 70 dB down): the echo sets the scale
        scene.noise[0].snr_db = 70.0
        echo_alone, _ = render(scene)
        babble_audio = work / "babble-alone.flac"
        soundfile.write(str(babble_audio), np.clip(pcm.astype(np.int32) - np.round(echo_alone * 32767).astype(np.int32),
                                                   -32768, 32767).astype(np.int16), FS)
        runs[BABBLE_ALONE] = (babble_audio, {})
    return {variant: talk_run(array, seconds, path, reference, robot_speech_s,
                              work / (variant.strip("_").replace("_", "-") or "default"), port, options, env, variant)
            for variant, (path, env) in runs.items()}


def talk_run(array: str, seconds: float, audio: Path, reference: Path, robot_speech_s: float, run_dir: Path,
             port: int, options: list[str], env: dict[str, str], variant: str) -> dict:
    from esiaf.tools import evaluation
    run_dir.mkdir(parents=True, exist_ok=True)
    fused, wall_s = evaluation.run_pipeline(audio, array, [*options, "--playback", str(reference), "--include-robot"],
                                            run_dir, port, "talk", env=env)
    robot = [f for f in fused if f.get("source") == "robot"]
    user = [f for f in fused if f.get("source") != "robot"]
    (run_dir / "fused.json").write_text(json.dumps(fused, indent=1) + "\n")
    figures = {"talk_s": seconds, "robot_speech_s": robot_speech_s,
               "user_utterances": len(user), "robot_utterances": len(robot), "wall_s": wall_s,
               "user_texts": [((f["anchor"].get("speech") or {}).get("hypotheses") or [{}])[0].get("text", "")
                              for f in user]}
    name = f"{array} {variant.strip('_')}" if variant else array
    print(f"talk {name}: {seconds:.0f} s of robot talk: {len(user)} fused user utterance(s) "
          f"{figures['user_texts']}, {len(robot)} tagged robot; {wall_s:.0f} s", flush=True)
    return figures


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    options = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--array", default="respeaker4")
    parser.add_argument("--backend", default="speex")
    parser.add_argument("--conditions", default="0:100,150:-100,300:100,300:-100", help="DELAY_MS:PPM pairs")
    parser.add_argument("--aec-seconds", type=float, default=45.0)
    parser.add_argument("--runs", type=int, default=2, help="rooms of the harness, each with and without the robot")
    parser.add_argument("--talk-s", type=float, default=300.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--port", type=int, default=23200)
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--skip", default="", help="parts to leave out: aec, eval, talk (comma-separated)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--slow-start", "--fast-start", action="store_true", dest="slow_start",
                        help="also run the canceller as it started before the fast start became its default "
                             "(bench/aec.py's SLOW_START), side by side")
    parser.add_argument("--gate-before", action="store_true",
                        help="also run the eval's robot half and the talk with the delay tracker's gate before "
                             "2026-11-28 (aec delay_outlier_ms 20), side by side")
    parser.add_argument("--babble-alone", action="store_true",
                        help="also run the talk's microphones without the robot's echo (its babble alone, at the "
                             "same scale; the player playing): what the babble makes of the figures")
    args = parser.parse_args(argv)
    variants = {"": {}, **({"_gate_before": GATE_BEFORE} if args.gate_before else {})}
    from esiaf.tools.evaluation import DEFAULT_PIPELINE
    pipeline = options if "--without" in options else DEFAULT_PIPELINE + options
    skip = set(filter(None, args.skip.split(",")))
    work = args.workdir or Path(tempfile.mkdtemp(prefix="esiaf-robot-speaks-"))
    work.mkdir(parents=True, exist_ok=True)
    conditions = [(float(d), float(p)) for d, p in (c.split(":") for c in args.conditions.split(","))]
    started = time.monotonic()
    report: dict = {"array": args.array, "backend": args.backend, "pipeline": pipeline}
    if "aec" not in skip:
        report["aec"] = canceller_part(args.array, conditions, args.aec_seconds, args.seed, args.backend,
                                       args.slow_start)
    if "eval" not in skip:
        report["eval"] = eval_part(args.array, args.runs, args.seed, work / "eval", args.port, pipeline, variants)
    if "talk" not in skip:
        report["talk"] = talk_part(args.array, args.talk_s, args.seed, work / "talk", args.port + 1, pipeline,
                                   variants, args.babble_alone)
    print(f"\n{'target':<62} {'measured':<40} goal")
    lines: list[tuple[str, str, str]] = []
    values: dict[str, float] = {}
    for row in report.get("aec", []):
        key = f"aec_d{row['delay_ms']:g}_p{row['ppm']:g}" + (f"_{row['variant']}" if row.get("variant") else "")
        label = f"{row['delay_ms']:g} ms, {row['ppm']:+g} ppm" + (f" ({row['variant']})" if row.get("variant") else "")
        lines.append((f"ERLE from 1 s after the robot starts, {label}",
                      f"{row['erle_db']:.1f} dB (median {row['erle_median_db']:.1f}; 1 s after the delay is known "
                      f"{row['erle_converged_db']:.1f})", ">= 25 dB"))
        lines.append((f"canceller CPU, {label}",
                      f"{row['cpu_pct']:.2f} % of a core", "<= 10 %"))
        for name in ("erle_db", "erle_median_db", "erle_converged_db", "erle_restart_db", "cpu_pct"):
            values[f"{key}_{name}"] = row[name]
        values[f"{key}_recognised"], values[f"{key}_recognised_clean"] = row["recognised"], row["recognised_clean"]
    for variant, e in report.get("eval", {}).items():
        label = f" ({variant.strip('_').replace('_', ' ')})" if variant else ""
        lines.append((f"questions recognised while the robot speaks / without it{label}",
                      f"{e['overlapped_recognised_robot']}/{e['overlapped_recognised_silent']} "
                      f"({100 * e['double_talk_ratio']:.0f} %) of {e['overlapped']}", ">= 80 %"))
        lines.append((f"person's direction within 15° while the robot speaks{label}",
                      f"{100 * e['overlapped_directions_within_15']:.0f} % of {e['overlapped']}", ">= 85 %"))
        values.update({f"eval_{k}{variant}": v for k, v in e.items()})
    for variant, t in report.get("talk", {}).items():
        label = f" ({variant.strip('_').replace('_', ' ')})" if variant else ""
        lines.append((f"fused user utterances of the robot's own speech, {t['talk_s']:.0f} s of talk{label}",
                      f"{t['user_utterances']} ({t['robot_utterances']} tagged robot)", "0"))
        values.update({f"talk_{k}{variant}": v for k, v in t.items() if k != "user_texts"})
    for name, measured, goal in lines:
        print(f"{name:<62} {measured:<40} {goal}")
    print(f"elapsed_s={time.monotonic() - started:.0f}")
    for name, value in values.items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

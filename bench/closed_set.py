"""Closed-set decoding by Whisper's acoustic model (esiaf_services/asr/closed_set.py), on true segments.

Renders rooms as ``esiaf eval robocup`` does (its ``make_scene``: the array in a shoebox room, babble
and kitchen noise at 5-15 dB), once with the RoboCup questions and once with speech outside them
(``bench/data/out_of_set.txt`` and the questions' answers), cuts each utterance from the first
microphone (its true span ± 0.2 s, as the harness's oracle row), and decodes each with

- nearest text: Whisper's free transcript matched to the nearest question (``matching.py``);
- acoustic: :class:`ClosedSetDecoder`, the shortlist scored by the model.

It prints, per utterance, the free transcript, the chosen sentence and the two rejection features
(the best sentence's log-probability per token, and its distance below the free transcript's per
token), then the questions recognised, the out-of-set speech accepted and the CPU time per
utterance, over a grid of rejection thresholds: how the defaults were chosen.

    nice -n 10 python bench/closed_set.py --runs 4 --seed 2     # calibration rooms (the harness uses seed 1)
"""
from __future__ import annotations

import argparse
import pickle
import subprocess
import time
from pathlib import Path

import numpy as np

from esiaf_services.asr.closed_set import ClosedSetDecoder
from esiaf_services.asr.matching import SentenceMatcher, normalise
from esiaf_services.asr.whisper import WhisperRecognizer

OUT_OF_SET = Path(__file__).resolve().parent / "data" / "out_of_set.txt"


def segments(seed: int, runs: int, arrays: list[str], cache: Path | None) -> list[dict]:
    """The utterances of ``runs`` rooms per array, in set and out of set, each cut from microphone 1."""
    if cache is not None and cache.is_file():
        return pickle.loads(cache.read_bytes())
    from esiaf.scenes import render
    from esiaf.tools.evaluation import DATA, make_scene, read_questions_and_answers
    questions = read_questions_and_answers(DATA)
    lines = OUT_OF_SET.read_text().splitlines()
    outside = [line.strip() for line in lines if line.strip() and not line.startswith("#")]
    outside += [answer for _, answer in questions]
    # the out-of-set rooms keep the questions' answers as babble
    outside_rows = [(sentence, questions[k % len(questions)][1]) for k, sentence in enumerate(outside)]
    work = Path(f"/tmp/esiaf-closed-set-{seed}")
    work.mkdir(exist_ok=True)
    items = []
    for array in arrays:
        for index in range(runs):
            for kind, rows, room_seed in (("in", questions, seed), ("out", outside_rows, seed + 100)):
                scene, _, snr_db = make_scene(index, room_seed, array, (5.0, 15.0), DATA, work, rows)
                signals, truth = render(scene)
                for u in truth["utterances"]:
                    first, last = int(max(0.0, u["start_s"] - 0.2) * 16000), int((u["end_s"] + 0.2) * 16000)
                    items.append({"kind": kind, "text": u["text"], "snr_db": snr_db, "array": array,
                                  "audio": np.clip(signals[first:last, 0], -1, 1).astype(np.float32)})
                print(f"rendered {array} room {index + 1} ({kind} set), SNR {snr_db:.1f} dB", flush=True)
    if cache is not None:
        cache.write_bytes(pickle.dumps(items))
    return items


def room_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the rooms the closed-set benches render (``segments``)."""
    parser.add_argument("--runs", type=int, default=4, help="rooms per array (each: 10 in-set, 10 out-of-set)")
    parser.add_argument("--seed", type=int, default=2, help="rooms' seed (default 2; the harness's rooms are seed 1)")
    parser.add_argument("--array", action="append", help="array preset (default: pepper4 and respeaker4)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    room_arguments(parser)
    parser.add_argument("--shortlist", type=int, default=6)
    parser.add_argument("--beam-size", type=int, default=1, help="the free decode's beam (default 1, the asr's)")
    parser.add_argument("--n-best", type=int, default=1, help="its hypotheses the shortlist is drawn from")
    parser.add_argument("--before", action="store_true",
                        help="also decode each utterance, in turn with the above, as before 2026-11-28 (beam 3, "
                             "3 hypotheses, 2 s of pad) and print both summaries")
    parser.add_argument("--threads", type=int, default=1, help="CTranslate2's threads (default 1)")
    parser.add_argument("--grammar", action="store_true",
                        help="the sentences of the robocup grammar (lower case, as the asr scores them with --grammar "
                             "robocup) rather than questions.tsv's")
    parser.add_argument("--cache", type=Path, help="keep the rendered utterances in this file (and reuse them)")
    args = parser.parse_args()
    from esiaf.tools.evaluation import DATA, read_questions_and_answers
    questions = [q for q, _ in read_questions_and_answers(DATA)]
    matcher = SentenceMatcher(questions)
    if args.grammar:
        from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
        matcher = SentenceMatcher.from_file(ROBOCUP_GRAMMAR, 0.6)
    items = segments(args.seed, args.runs, args.array or ["pepper4", "respeaker4"], args.cache)
    whisper = WhisperRecognizer(threads=args.threads)
    decoders = {"": ClosedSetDecoder(whisper.model, matcher, args.shortlist, args.beam_size, args.n_best)}
    if args.before:
        decoders["before"] = ClosedSetDecoder(whisper.model, matcher, args.shortlist, 3, 3, pad_s=2.0)
    rows: dict[str, list[dict]] = {name: [] for name in decoders}
    for decoder in decoders.values():
        decoder.decode(items[0]["audio"])  # warm up
    for item in items:
        for name, decoder in decoders.items():
            row = decode(decoder, matcher, item)
            if row is not None:
                rows[name].append(row)
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    for name, kept in rows.items():
        summarise(kept, name or f"beam {args.beam_size}, {args.n_best} hypotheses, pad {decoders[''].pad_s:g} s")


def decode(decoder: ClosedSetDecoder, matcher: SentenceMatcher, item: dict) -> dict | None:
    started, wall = time.process_time(), time.perf_counter()
    result = decoder.decode(item["audio"])
    cpu_s, wall_s = time.process_time() - started, time.perf_counter() - wall
    if result is None:
        return None
    best = result.ranked[0]
    near = matcher.match(result.raw_text)
    row = {"kind": item["kind"], "cpu_s": cpu_s, "wall_s": wall_s, "per_token": result.per_token,
           "below": result.below_raw, "same": normalise(result.raw_text) == normalise(best.sentence),
           "right": normalise(best.sentence) == normalise(item["text"]),
           "listed": any(normalise(s.sentence) == normalise(item["text"]) for s in result.ranked),
           "nearest": near.in_set and normalise(near.sentence) == normalise(item["text"]), "near_in": near.in_set}
    print(f"{item['kind']:>3} {item['snr_db']:5.1f} dB {'right' if row['right'] else 'wrong':>5} "
          f"{'listed' if row['listed'] else '':>6} per token {row['per_token']:6.2f} "
          f"below free {row['below']:5.2f} "
          f"cpu {cpu_s:.2f} s | {result.raw_text!r} | {best.sentence!r}", flush=True)
    return row


def summarise(rows: list[dict], label: str) -> None:
    inside = [r for r in rows if r["kind"] == "in"]
    outside = [r for r in rows if r["kind"] == "out"]
    cpu = np.array([r["cpu_s"] for r in rows])
    wall = np.array([r["wall_s"] for r in rows])
    print(f"\n== {label}: {len(inside)} in-set, {len(outside)} out-of-set utterances; "
          f"CPU per utterance p50 {np.median(cpu):.3f} s, mean {cpu.mean():.3f} s; wall p50 {np.median(wall):.3f} s")
    print(f"nearest text: {np.mean([r['nearest'] for r in inside]):.1%} recognised, "
          f"{np.mean([r['near_in'] for r in outside]):.1%} out-of-set accepted")
    print(f"acoustic, no rejection: {np.mean([r['right'] for r in inside]):.1%} recognised "
          f"(right sentence in the shortlist: {np.mean([r['listed'] for r in inside]):.1%})")
    print("min per token  max below free  recognised  out-of-set accepted")
    for floor in (-2.5, -3.0, -3.5, -4.0, -4.5, -99.0):
        for ceiling in (1.5, 2.0, 2.5, 3.0, 99.0):
            def accepted(r, floor=floor, ceiling=ceiling):
                return r["same"] or (r["per_token"] >= floor and r["below"] <= ceiling)
            print(f"{floor:14.1f} {ceiling:15.1f} {np.mean([r['right'] and accepted(r) for r in inside]):11.1%} "
                  f"{np.mean([accepted(r) for r in outside]):20.1%}")

if __name__ == "__main__":
    main()

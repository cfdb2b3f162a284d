"""The cascade's out-of-set speech: does pocketsphinx agree with Whisper's second opinion?

``bench/cascade.py`` measures the cascade (``second_opinion: whisper``: Whisper's closed set asked only
where pocketsphinx says out of set) on the true segments of rendered rooms: it recognises ~9 points more
questions than pocketsphinx alone and takes ~6 points more out-of-set speech for a question. Whisper's
own thresholds did not buy that back. This bench collects, on the same segments (denoised, as the asr
hears them), what each recogniser says of each utterance, so that rules combining the two can be tried:

- pocketsphinx (the ``robocup`` grammar, the phone loop): its best sentence (whole or cut short), its
  ``confidence``, its n-best texts;
- where pocketsphinx rejects (the cascade asks Whisper only there): Whisper (``ClosedSetDecoder`` with
  the asr's second-opinion settings over the grammar's sentences), its best sentence, its rejection
  features, the runner-up and the free transcript; and pocketsphinx's ``confidence`` of Whisper's best
  sentence: the utterance decoded again with a grammar of that one sentence, against the phone loop
  (``PocketsphinxRecognizer.sentence_confidence``);

and prints, for each seed given, pocketsphinx alone, the cascade as it is, and the cascade where
Whisper's sentence is taken only when pocketsphinx agrees (each rule over a grid), side by side.

    nice -n 10 python -m bench.cascade_agreement --seed 2 --seed 3 --cache /tmp/seg{seed}.pkl --rows /tmp/rows{seed}.pkl
"""
from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench.closed_set import segments
from bench.closed_set_pocketsphinx import denoise_all
from esiaf_services.asr.closed_set import ClosedSetDecoder
from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
from esiaf_services.asr.matching import SentenceMatcher, normalise
from esiaf_services.asr.recognizer import MIN_CONFIDENCE, PocketsphinxRecognizer
from esiaf_services.asr.service import WhisperSettings
from esiaf_services.asr.whisper import WhisperRecognizer

SENTENCE_CONFIDENCE = (-99.0, -3.0, -2.5, -2.25, -2.0, -1.8)
OVERLAP = (0.0, 0.3, 0.5, 0.6, 0.7, 0.8)


def words(text: str) -> list[str]:
    return normalise(text)


def overlap(first: str, second: str) -> float:
    """The share of the longer text's words that the other has too (each word counted once a time)."""
    a, b = words(first), words(second)
    if not a or not b:
        return 0.0
    rest, shared = list(b), 0
    for word in a:
        if word in rest:
            rest.remove(word)
            shared += 1
    return shared / max(len(a), len(b))


def collect(items: list[dict], clean: list[np.ndarray], sphinx: PocketsphinxRecognizer,
            decoder: ClosedSetDecoder) -> list[dict]:
    rows = []
    for item, audio in zip(items, clean, strict=True):
        pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2").tobytes()
        started = time.process_time()
        hypotheses = sphinx.recognise(pcm)
        ps_cpu = time.process_time() - started
        best = hypotheses[0] if hypotheses else None
        rejected = best is None or best.whole is False or (best.confidence is not None and
                                                           best.confidence < MIN_CONFIDENCE)
        started = time.process_time()
        result = decoder.decode(audio) if rejected else None  # the cascade asks Whisper only there
        wh_cpu = time.process_time() - started
        row = {"kind": item["kind"], "truth": " ".join(normalise(item["text"])), "text": item["text"],
               "snr_db": item["snr_db"], "array": item["array"], "ps_cpu": ps_cpu, "wh_cpu": wh_cpu,
               "ps_best": best.text if best else "", "ps_whole": bool(best and best.whole),
               "ps_confidence": best.confidence if best and best.confidence is not None else -np.inf,
               "ps_word_confidence": best.word_confidence if best and best.word_confidence is not None else -np.inf,
               "ps_nbest": [h.text for h in hypotheses], "ps_rejected": rejected,
               "wh_best": "", "wh_in_set": False, "wh_per_token": -np.inf, "wh_below": np.inf, "wh_margin": 0.0,
               "wh_raw": "", "wh_second": "", "agree_confidence": -np.inf, "agree_cpu": 0.0}
        if result is not None:
            row.update(wh_best=result.ranked[0].sentence, wh_in_set=result.in_set, wh_per_token=result.per_token,
                       wh_below=result.below_raw, wh_margin=min(result.margin, 99.0), wh_raw=result.raw_text,
                       wh_second=result.ranked[1].sentence if len(result.ranked) > 1 else "")
            started = time.process_time()
            confidence = sphinx.sentence_confidence(pcm, result.ranked[0].sentence)
            row["agree_cpu"] = time.process_time() - started
            row["agree_confidence"] = confidence if confidence is not None else -np.inf
        rows.append(row)
        print(f"{row['kind']:>3} {row['snr_db']:5.1f} dB | {item['text']!r} | ps {row['ps_best']!r} "
              f"{'rejected' if rejected else 'taken'} {row['ps_confidence']:.2f} | whisper {row['wh_best']!r} "
              f"{'in' if row['wh_in_set'] else 'out'} | ps on whisper's {row['agree_confidence']:.2f}", flush=True)
    return rows


def said(row: dict, rule) -> str:
    """The question answered under ``rule`` (None: pocketsphinx alone; else the cascade where Whisper's
    sentence is taken only if ``rule(row)``); "" where out of set."""
    if not row["ps_rejected"]:
        return " ".join(normalise(row["ps_best"]))
    if rule is None or not row["wh_in_set"] or not rule(row):
        return ""
    return " ".join(normalise(row["wh_best"]))


def scores(rows: list[dict], rule, cascade: bool = True) -> tuple[float, float, float, float, float]:
    inside = [r for r in rows if r["kind"] == "in"]
    outside = [r for r in rows if r["kind"] == "out"]
    how = rule if cascade else None
    right = np.mean([said(r, how) == r["truth"] for r in inside])
    wrong = np.mean([bool(said(r, how)) and said(r, how) != r["truth"] for r in inside])
    accepted = np.mean([bool(said(r, how)) for r in outside])
    # the cascade: Whisper where pocketsphinx rejects; the check where Whisper takes a sentence
    checks = rule is not None and rule is not ALL
    cpu = np.array([r["ps_cpu"] + ((r["wh_cpu"] + (r["agree_cpu"] if checks and r["wh_in_set"] else 0.0))
                                   if cascade and r["ps_rejected"] else 0.0) for r in rows])
    return float(right), float(wrong), float(accepted), float(np.median(cpu)), float(cpu.mean())


def ALL(row: dict) -> bool:  # the cascade as it is: Whisper's answer always taken
    return True


def rules() -> dict[str, object]:
    grid: dict[str, object] = {"pocketsphinx alone": None, "cascade as it is": ALL}
    grid["same sentence as pocketsphinx's best"] = lambda r: " ".join(normalise(r["wh_best"])) == " ".join(
        normalise(r["ps_best"]))
    grid["in pocketsphinx's n-best"] = lambda r: " ".join(normalise(r["wh_best"])) in {
        " ".join(normalise(t)) for t in r["ps_nbest"]}
    for least in OVERLAP[1:]:
        grid[f"word overlap with ps's best >= {least}"] = lambda r, least=least: overlap(r["wh_best"],
                                                                                          r["ps_best"]) >= least
    for floor in SENTENCE_CONFIDENCE[1:]:
        grid[f"ps confidence of whisper's >= {floor}"] = lambda r, floor=floor: r["agree_confidence"] >= floor
    for floor in (-3.0, -2.5):
        for least in (0.3, 0.5):
            grid[f"ps conf of whisper's >= {floor} or overlap >= {least}"] = \
                lambda r, floor=floor, least=least: r["agree_confidence"] >= floor or overlap(
                    r["wh_best"], r["ps_best"]) >= least
    for floor in (-3.0, -2.5, -2.0):
        for least in (0.3, 0.5):
            grid[f"ps conf of whisper's >= {floor} and overlap >= {least}"] = \
                lambda r, floor=floor, least=least: r["agree_confidence"] >= floor and overlap(
                    r["wh_best"], r["ps_best"]) >= least
    for gap in (0.5, 1.0, 1.5):
        grid[f"ps conf of whisper's >= ps best's - {gap}"] = \
            lambda r, gap=gap: r["agree_confidence"] >= r["ps_confidence"] - gap
    return grid


def report(by_seed: dict[int, list[dict]]) -> None:
    seeds = sorted(by_seed)
    head = " | ".join(f"seed {s}: right wrong oos  cpu p50/mean" for s in seeds)
    print(f"\n{'rule':>55} | {head}")
    for name, rule in rules().items():
        cells = []
        for s in seeds:
            right, wrong, accepted, p50, mean = scores(by_seed[s], rule, cascade=rule is not None)
            cells.append(f"{right:6.1%} {wrong:5.1%} {accepted:5.1%} {p50:5.2f}/{mean:4.2f} s")
        print(f"{name:>55} | " + " | ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, action="append", help="rooms' seed (repeat; default 2 and 3)")
    parser.add_argument("--runs", type=int, default=4, help="rooms per array (each: 10 in-set, 10 out-of-set)")
    parser.add_argument("--cache", help="the rendered utterances of each seed, kept in this file ({seed} in it)")
    parser.add_argument("--rows", help="keep what the recognisers said of each seed in this file ({seed} in it), "
                        "and reuse it")
    args = parser.parse_args()
    seeds = args.seed or [2, 3]
    by_seed: dict[int, list[dict]] = {}
    for seed in seeds:
        kept = Path(args.rows.format(seed=seed)) if args.rows else None
        if kept is not None and kept.is_file():
            by_seed[seed] = pickle.loads(kept.read_bytes())
            continue
        if not by_seed.get(-1):
            sphinx = PocketsphinxRecognizer(16000, grammar=ROBOCUP_GRAMMAR, phone_loop=True)
            w = WhisperSettings()
            matcher = SentenceMatcher.from_file(ROBOCUP_GRAMMAR, 0.6, 0.7)  # the asr's second opinion: the grammar's
            decoder = ClosedSetDecoder(WhisperRecognizer(threads=1).model, matcher, w.shortlist,
                                       w.scoring_beam_size, 1, min_per_token=w.min_logprob_per_token)
            by_seed[-1] = []  # made
        cache = Path(args.cache.format(seed=seed)) if args.cache else None
        items = segments(seed, args.runs, ["pepper4", "respeaker4"], cache)
        clean = denoise_all(items, cache.with_suffix(".denoised.pkl") if cache else None)
        by_seed[seed] = collect(items, clean, sphinx, decoder)
        if kept is not None:
            kept.write_bytes(pickle.dumps(by_seed[seed]))
    by_seed.pop(-1, None)
    report(by_seed)


if __name__ == "__main__":
    main()

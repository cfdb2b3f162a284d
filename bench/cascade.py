"""Both recognisers on one closed set: how much a cascade of pocketsphinx and Whisper would gain.

On the harness (``esiaf eval robocup --runs 6 --seed 1``, docs/benchmarks.md) pocketsphinx (denoised,
grammar, out-of-set check) and Whisper tiny.en (acoustic scoring of a shortlist) each recognise about
four questions in five, and when either answers it is almost never a wrong question: what each loses it
loses by saying "out of set". They lose different questions. This bench measures, on the same rendered
utterances as ``bench/closed_set.py`` and ``bench/closed_set_pocketsphinx.py`` (their true spans on
microphone 1, in set and out of set), what a cascade would do:

- pocketsphinx as the service runs it (the vad's utterance denoised by the denoiser's filter, the
  ``robocup`` grammar, a whole sentence and ``min_confidence``), and where it says out of set,
- Whisper as the service runs it (the utterance as the vad passes it, ``ClosedSetDecoder`` with the
  service's shortlist, beam and rejection), or on the denoised utterance (what the asr service would
  have at hand if the cascade ran inside it, after the denoiser),

and prints, for each recogniser alone and for the cascade: questions recognised, questions answered
with a wrong question, out-of-set speech accepted, and the CPU per utterance (the cascade's Whisper
runs only where pocketsphinx rejects).

    nice -n 10 python -m bench.cascade --runs 4 --seed 2 --cache /tmp/seg.pkl
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench.closed_set import room_arguments, segments
from bench.closed_set_pocketsphinx import denoise_all
from esiaf_services.asr.closed_set import ClosedSetDecoder
from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
from esiaf_services.asr.matching import SentenceMatcher, normalise
from esiaf_services.asr.recognizer import MIN_CONFIDENCE, PocketsphinxRecognizer
from esiaf_services.asr.service import WhisperSettings
from esiaf_services.asr.whisper import WhisperRecognizer


def pocketsphinx_answer(recogniser: PocketsphinxRecognizer, audio: np.ndarray) -> str:
    """The question pocketsphinx answers ("" where it says out of set), as the service decides."""
    pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2").tobytes()
    hypotheses = recogniser.recognise(pcm)
    best = hypotheses[0] if hypotheses else None
    if best is None or not best.text or best.whole is False or (
            best.confidence is not None and best.confidence < MIN_CONFIDENCE):
        return ""
    return best.text


def whisper_answer(decoder: ClosedSetDecoder, audio: np.ndarray) -> tuple[str, dict]:
    """The question Whisper's acoustic scoring answers ("" where it says out of set), and the best
    sentence with its rejection features (for the cascade's own thresholds)."""
    result = decoder.decode(audio)
    if result is None:
        return "", {"best": "", "same": False, "per_token": -np.inf, "below": np.inf}
    best = result.ranked[0].sentence
    features = {"best": normalise(best), "same": normalise(result.raw_text) == normalise(best),
                "per_token": result.per_token, "below": result.below_raw}
    return (best if result.in_set else ""), features


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    room_arguments(parser)
    parser.add_argument("--cache", type=Path, help="keep the rendered utterances in this file (and reuse them); "
                        "the denoised ones go beside it")
    args = parser.parse_args()
    from esiaf.tools.evaluation import DATA, read_questions_and_answers
    matcher = SentenceMatcher([q for q, _ in read_questions_and_answers(DATA)])
    items = segments(args.seed, args.runs, args.array or ["pepper4", "respeaker4"], args.cache)
    clean = denoise_all(items, args.cache.with_suffix(".denoised.pkl") if args.cache else None)
    sphinx = PocketsphinxRecognizer(16000, grammar=ROBOCUP_GRAMMAR, phone_loop=True)
    w = WhisperSettings()
    decoder = ClosedSetDecoder(WhisperRecognizer(threads=1).model, matcher, w.shortlist, w.beam_size,
                               min_per_token=w.min_logprob_per_token)
    pocketsphinx_answer(sphinx, clean[0])  # warm up
    whisper_answer(decoder, items[0]["audio"])
    rows = []
    for item, denoised in zip(items, clean, strict=True):
        started = time.process_time()
        ps = pocketsphinx_answer(sphinx, denoised)
        ps_cpu = time.process_time() - started
        started = time.process_time()
        wh, _ = whisper_answer(decoder, item["audio"])
        wh_cpu = time.process_time() - started
        wh_denoised, features = whisper_answer(decoder, denoised)  # the service's second opinion hears this
        rows.append({"kind": item["kind"], "truth": normalise(item["text"]), "ps": normalise(ps), "wh": normalise(wh),
                     "wh_denoised": normalise(wh_denoised), "ps_cpu": ps_cpu, "wh_cpu": wh_cpu, **features})
        print(f"{item['kind']:>3} {item['snr_db']:5.1f} dB | {item['text']!r} | ps {ps!r} | whisper {wh!r}", flush=True)

    def answers(row: dict, how: str) -> tuple[str, float]:
        if how == "pocketsphinx":
            return row["ps"], row["ps_cpu"]
        if how == "whisper":
            return row["wh"], row["wh_cpu"]
        if how == "whisper, denoised":
            return row["wh_denoised"], row["wh_cpu"]
        if how == "cascade, whisper denoised":
            return (row["ps"], row["ps_cpu"]) if row["ps"] else (row["wh_denoised"], row["ps_cpu"] + row["wh_cpu"])
        # the cascade: Whisper only where pocketsphinx says out of set
        return (row["ps"], row["ps_cpu"]) if row["ps"] else (row["wh"], row["ps_cpu"] + row["wh_cpu"])

    inside = [r for r in rows if r["kind"] == "in"]
    outside = [r for r in rows if r["kind"] == "out"]
    print(f"\n{len(inside)} in-set, {len(outside)} out-of-set utterances (microphone 1, true spans)")
    print(f"{'':>40} {'recognised':>10} {'wrong question':>14} {'out of set accepted':>19} {'CPU p50 / mean':>16}")
    for how in ("pocketsphinx", "whisper", "whisper, denoised", "cascade: pocketsphinx, then whisper",
                "cascade, whisper denoised"):
        said = [answers(r, how) for r in inside]
        right = np.mean([a == r["truth"] for (a, _), r in zip(said, inside, strict=True)])
        wrong = np.mean([bool(a) and a != r["truth"] for (a, _), r in zip(said, inside, strict=True)])
        accepted = np.mean([bool(answers(r, how)[0]) for r in outside])
        cpu = np.array([answers(r, how)[1] for r in rows])
        print(f"{how:>40} {right:10.1%} {wrong:14.1%} {accepted:19.1%} "
              f"{np.median(cpu):7.2f} / {cpu.mean():.2f} s")
    print("\nthe cascade (Whisper on the denoised audio, as in the service) with its own rejection for Whisper:")
    print(f"{'min per token':>14} {'max below free':>15} {'recognised':>10} {'out of set accepted':>19}")
    for floor in (-4.0, -3.5, -3.0, -2.5, -2.0):
        for ceiling in (99.0, 2.5, 2.0, 1.5):
            def answer(r: dict, floor: float = floor, ceiling: float = ceiling) -> str:
                if r["ps"]:
                    return r["ps"]
                taken = r["same"] or (r["per_token"] >= floor and r["below"] <= ceiling)
                return r["best"] if taken else ""
            right = np.mean([answer(r) == r["truth"] for r in inside])
            accepted = np.mean([bool(answer(r)) for r in outside])
            print(f"{floor:14.1f} {ceiling:15.1f} {right:10.1%} {accepted:19.1%}")


if __name__ == "__main__":
    main()

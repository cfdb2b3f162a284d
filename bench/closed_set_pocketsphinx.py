"""Out-of-set rejection for pocketsphinx with the RoboCup grammar, on the true segments of rendered rooms.

The segments are those of ``bench/closed_set.py`` (its ``segments``: rooms as ``esiaf eval robocup``
renders them, 5-15 dB, in set = the 50 questions, out of set = ``bench/data/out_of_set.txt`` and the
questions' answers, each cut from microphone 1 ± 0.2 s), decoded raw and through the denoiser
service's filter (``ChannelFilter``, fed 20 ms chunks and flushed at each segment's end, one filter
for all segments in order, as ``bench/denoise.py``). Each segment is decoded whole with the grammar
(``PocketsphinxRecognizer.recognise``), once as the service did before (no rejection) and once with the
phone loop (``phone_loop=True``: pocketsphinx's allphone search, a second decoder fed the same audio),
and these features of the grammar's answer are kept:

- ``posterior``: the best path's lattice posterior (``Decoder.hyp().prob``; no extra decoding);
- ``path``: the grammar path's log-likelihood per frame, in nats (pocketsphinx scores each frame
  relative to its best senone, so this is already a crude confidence; no extra decoding);
- ``confidence``: over the frames of the sentence's words (silences left out), their log-likelihood
  minus the phone loop's over the same frames, per frame, in nats (``Hypothesis.confidence``);
- ``word``: the same for the sentence's worst word (``Hypothesis.word_confidence``);
- ``whole``: whether the answer is a whole sentence of the grammar: when no path reaches the grammar's
  end, pocketsphinx gives the best path so far, a sentence cut short (``Hypothesis.whole``).

It prints per segment the sentence and features, then, raw and denoised, the questions recognised
and the out-of-set speech accepted (a sentence given for it) by each rule over a grid of thresholds,
and the CPU per utterance of the decode without and with the phone loop.

    nice -n 10 python -m bench.closed_set_pocketsphinx --runs 4 --seed 2 --cache /tmp/seg.pkl
"""
from __future__ import annotations

import argparse
import math
import pickle
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.closed_set import room_arguments, segments  # noqa: E402
from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR  # noqa: E402
from esiaf_services.asr.matching import normalise  # noqa: E402
from esiaf_services.asr.recognizer import PocketsphinxRecognizer  # noqa: E402

CHUNK = 320  # 20 ms at 16 kHz, as the grabber sends
POSTERIORS = (0.0, 0.5, 0.8, 0.9, 0.95)
PATH = (-99.0, -4.5, -4.0, -3.5, -3.0, -2.5)
CONFIDENCE = (-99.0, -3.0, -2.5, -2.25, -2.0, -1.9, -1.8, -1.7, -1.6, -1.5, -1.4, -1.3, -1.2, -1.0)
WORD = (-99.0, -6.0, -5.5, -5.0, -4.5, -4.25, -4.0, -3.75, -3.5)


def denoise_all(items: list[dict], cache: Path | None) -> list[np.ndarray]:
    """Each item's audio through one denoiser filter, segment after segment."""
    if cache is not None and cache.is_file():
        return pickle.loads(cache.read_bytes())
    from esiaf_services.denoiser.filter import ChannelFilter
    f = ChannelFilter(16000)
    out = []
    for item in items:
        audio = item["audio"]
        out.append(np.concatenate([f.process(audio[i:i + CHUNK]) for i in range(0, len(audio), CHUNK)]
                                  + [f.flush()]))
    if cache is not None:
        cache.write_bytes(pickle.dumps(out))
    return out


def features(plain: PocketsphinxRecognizer, with_loop: PocketsphinxRecognizer, audio: np.ndarray) -> dict:
    """The grammar's answer for one segment (decoded whole) and its rejection features; the CPU of the
    decode without and with the phone loop."""
    pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2").tobytes()
    started = time.process_time()
    plain.recognise(pcm)
    decoded = time.process_time()
    hypotheses = with_loop.recognise(pcm)
    looped = time.process_time()
    best = hypotheses[0] if hypotheses else None
    return {"text": best.text if best else "", "cpu_decode_s": decoded - started, "cpu_with_loop_s": looped - decoded,
            "posterior": with_loop.posterior() if best else 0.0,
            "path": with_loop.path_score_per_frame() if best else -math.inf,
            "confidence": best.confidence if best else -math.inf,
            "word": best.word_confidence if best else -math.inf, "whole": bool(best and best.whole)}


def table(rows: list[dict], name: str) -> None:
    inside = [r for r in rows if r["kind"] == "in"]
    outside = [r for r in rows if r["kind"] == "out"]

    def line(label: str, accept) -> None:
        recognised = np.mean([r["right"] and accept(r) for r in inside])
        accepted = np.mean([bool(r["text"]) and accept(r) for r in outside])
        print(f"{label:>32} {recognised:11.1%} {accepted:20.1%}")
    print(f"\n== {name}: {len(inside)} in set, {len(outside)} out of set")
    for key in ("cpu_decode_s", "cpu_with_loop_s"):
        cpu = np.array([r[key] for r in rows]) * 1000
        print(f"{key[4:-2]:>12} CPU per utterance: p50 {np.median(cpu):.1f} ms, mean {cpu.mean():.1f} ms")
    print(f"{'rule':>32} {'recognised':>11} {'out-of-set accepted':>20}")
    line("none (the service before)", lambda r: True)
    line("whole sentence", lambda r: r["whole"])
    for floor in POSTERIORS[1:]:
        line(f"posterior >= {floor:.2f}", lambda r, floor=floor: r["posterior"] >= floor)
    for floor in PATH[1:]:
        line(f"path >= {floor:.2f}", lambda r, floor=floor: r["path"] >= floor)
    for floor in CONFIDENCE[1:]:
        line(f"confidence >= {floor:.2f}", lambda r, floor=floor: r["confidence"] >= floor)
    for floor in WORD[1:]:
        line(f"word >= {floor:.2f}", lambda r, floor=floor: r["word"] >= floor)
    print("whole sentence and")
    for floor in CONFIDENCE[1:]:
        line(f"confidence >= {floor:.2f}", lambda r, floor=floor: r["whole"] and r["confidence"] >= floor)
    for floor in WORD[1:]:
        line(f"word >= {floor:.2f}", lambda r, floor=floor: r["whole"] and r["word"] >= floor)
    for floor in CONFIDENCE:
        for word in WORD[1:]:
            line(f"confidence >= {floor:.2f}, word >= {word:.2f}", lambda r, floor=floor, word=word:
                 r["whole"] and r["confidence"] >= floor and r["word"] >= word)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    room_arguments(parser)
    parser.add_argument("--cache", type=Path, help="keep the rendered utterances in this file (and reuse them); "
                        "the denoised ones go beside it")
    parser.add_argument("--conditions", default="raw,denoised", help="raw, denoised or both (default)")
    parser.add_argument("--quiet", action="store_true", help="only the tables")
    args = parser.parse_args()
    items = segments(args.seed, args.runs, args.array or ["pepper4", "respeaker4"], args.cache)
    conditions = args.conditions.split(",")
    clean = denoise_all(items, args.cache.with_suffix(".denoised.pkl") if args.cache else None) \
        if "denoised" in conditions else []
    for name, audios in (("raw", [item["audio"] for item in items]), ("denoised", clean)):
        if name not in conditions:
            continue
        plain = PocketsphinxRecognizer(16000, grammar=ROBOCUP_GRAMMAR)
        with_loop = PocketsphinxRecognizer(16000, grammar=ROBOCUP_GRAMMAR, phone_loop=True)
        features(plain, with_loop, audios[0])  # warm up
        rows = []
        for item, audio in zip(items, audios, strict=True):
            row = {"kind": item["kind"], **features(plain, with_loop, audio)}
            row["right"] = bool(row["text"]) and normalise(row["text"]) == normalise(item["text"])
            rows.append(row)
            if not args.quiet:
                print(f"{name} {item['kind']:>3} {item['snr_db']:5.1f} dB {'right' if row['right'] else 'wrong':>5} "
                      f"posterior {row['posterior']:5.3f} path {row['path']:6.2f} confidence {row['confidence']:6.2f} "
                      f"word {row['word']:6.2f} {'whole' if row['whole'] else 'cut':>5} | {item['text']!r} | "
                      f"{row['text']!r}", flush=True)
        table(rows, name)


if __name__ == "__main__":
    main()

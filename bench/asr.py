"""Both recognisers side by side on real speech: word error, false matches, speed.

    python bench/asr.py [--worst N] [--n-best N]

Pocketsphinx (en-us language model, streamed as the service does) and Whisper tiny.en (the
asr-whisper extra) decode the transcribed clips of ../shared/data/speech (the pocketsphinx folder
and CMU ARCTIC). Word error is on normalised text (esiaf_services/asr/matching.py: case, punctuation,
numbers as words). False matches: each clip's transcript matched against the 50 RoboCup questions
(none of them is one) and counted when it is not refused as out of set. The time from segment
end to result is what each backend spends once the segment has closed (pocketsphinx: finishing its
streamed decode; Whisper: the whole decode). Ends with name=value lines; ``--worst N`` first
prints each backend's N clips with the most word errors (reference and transcript), to stderr.
``--n-best`` is Whisper's (1 by default: its first hypothesis is the same with any; the asr
service's default, 10, adds the second beam search to its CPU time).
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import csv  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import soundfile  # noqa: E402

from esiaf_services.asr.matching import SentenceMatcher, normalise, word_distance  # noqa: E402
from esiaf_services.asr.recognizer import PocketsphinxRecognizer  # noqa: E402
from esiaf_services.asr.service import resolve_grammar  # noqa: E402
from esiaf_services.asr.whisper import WhisperRecognizer  # noqa: E402

DATA = Path(os.environ.get("ESIAF_SHARED_DATA", REPO.parent / "shared" / "data"))


def clips() -> list[tuple[str, np.ndarray, str]]:
    rows = csv.DictReader((DATA / "manifest.tsv").open(), delimiter="\t")
    out = []
    for row in rows:
        if not row["path"].startswith("speech/") or not row["reference_transcript"]:
            continue
        path = DATA / row["path"]
        if path.suffix == ".raw":
            samples = np.fromfile(path, "<i2").astype(np.float32) / 32768
        else:
            samples, rate = soundfile.read(path, dtype="float32")
            if rate != 16000:
                continue
        folder = "cmu_arctic" if "cmu_arctic" in row["path"] else "pocketsphinx"
        out.append((folder, samples, row["reference_transcript"]))
    return out


def pocketsphinx_decoder():
    recognizer = PocketsphinxRecognizer()

    def decode(samples: np.ndarray) -> tuple[str, float]:
        pcm = (np.clip(samples, -1, 1) * 32767).astype("<i2").tobytes()
        recognizer.start()
        for i in range(0, len(pcm), 640):  # 20 ms chunks, as the service is fed
            recognizer.feed(pcm[i:i + 640])
        started = time.perf_counter()
        hypotheses = recognizer.finish()
        return (hypotheses[0].text if hypotheses else ""), time.perf_counter() - started
    return decode


def whisper_decoder(n_best: int = 1):
    recognizer = WhisperRecognizer(n_best=n_best)

    def decode(samples: np.ndarray) -> tuple[str, float]:
        started = time.perf_counter()
        result = recognizer.recognise(samples)
        return (result.hypotheses[0].text if result.hypotheses else ""), time.perf_counter() - started
    return decode


def main() -> None:
    parser = argparse.ArgumentParser(description="both recognisers side by side on real speech")
    parser.add_argument("--worst", type=int, default=0, metavar="N", help="print the N clips with most word errors")
    parser.add_argument("--n-best", type=int, default=1, metavar="N", help="Whisper's n_best (1)")
    args = parser.parse_args()
    if not (DATA / "manifest.tsv").is_file():
        raise SystemExit(f"bench/asr.py: no shared data at {DATA} (set ESIAF_SHARED_DATA)")
    material = clips()
    audio_s = sum(len(s) for _, s, _ in material) / 16000
    grammar = resolve_grammar("robocup")
    assert grammar is not None  # bundled
    matcher = SentenceMatcher.from_file(grammar, threshold=0.6)
    print(f"bench/asr: {len(material)} clips, {audio_s:.0f} s of speech", file=sys.stderr)
    lines = []
    for name, make in (("pocketsphinx", pocketsphinx_decoder), ("whisper", lambda: whisper_decoder(args.n_best))):
        decode = make()
        errors: dict[str, list[int]] = {}
        after_end_s, busy_s, false_matches = [], 0.0, 0
        worst: list[tuple[int, str, str, str]] = []
        for folder, samples, reference in material:
            cpu = time.process_time()
            text, tail_s = decode(samples)
            busy_s += time.process_time() - cpu
            after_end_s.append(tail_s)
            ref = normalise(reference)
            pair = errors.setdefault(folder, [0, 0])
            distance = word_distance(ref, normalise(text))
            worst.append((distance, folder, reference, text))
            pair[0] += distance
            pair[1] += len(ref)
            false_matches += bool(text) and matcher.match(text).in_set
        for distance, folder, reference, text in sorted(worst, key=lambda w: -w[0])[:args.worst]:
            print(f"bench/asr: {name} {distance} word errors ({folder}): {reference!r} heard {text!r}", file=sys.stderr)
        for folder, (e, n) in sorted(errors.items()):
            lines.append(f"{name}_wer_{folder}={e / n:.3f}")
        lines.append(f"{name}_false_matches={false_matches / len(material):.3f}")
        lines.append(f"{name}_cpu_rtf={busy_s / audio_s:.3f}")
        lines.append(f"{name}_after_segment_end_p50_ms={1000 * float(np.median(after_end_s)):.1f}")
        print(f"bench/asr: {name} done", file=sys.stderr)
    print("\n".join(lines))


if __name__ == "__main__":
    main()

"""The data set of bench/dataset.py: minutes of labelled speech with pauses, rendered for an array.

Like the thesis' data set (German samples with 3 s of silence between them), but with labels the
pipeline's analysers can be scored on. Each utterance is drawn at random (``seed``) from:

- **EmoDB** (``../shared/data/emodb``): the acted German utterances of the four emotions the
  emotion model knows (anger, happiness, neutral, sadness: 339 files), with their emotion and
  speaker gender; no text is scored (German, the recogniser's grammar is English);
- **RoboCup questions** (``../shared/data/robocup/questions.tsv``): spoken by flite with one of its
  voices (slt female; kal16, awb, rms male), with their text and gender.

Each is rendered on its own with :mod:`esiaf.scenes` (a 6 x 5 x 3 m room, RT60 0.4 s, the array
in the middle) from a random azimuth 1-2 m away, at the clip's own peak level (so that anger stays
louder than sadness), and placed in the timeline after a pause of 2.5-3.5 s; a white noise floor
(-66 dBFS RMS on each microphone, independent) keeps the pauses from being digital silence.
The rendering and its truth (JSON: per utterance its kind, span, azimuth, text, emotion and
gender) are cached under ``$TMPDIR/esiaf-dataset/<key>`` keyed by the parameters; a rerun with
the same parameters reads them back.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("ESIAF_SHARED_DATA") or REPO.parent / "shared" / "data")
VERSION = 1  # of the recipe: change it when the rendering changes, so that old caches are not reused
RATE_HZ = 16000
EMOTIONS = {"anger": "angry", "happiness": "happy", "neutral": "neutral", "sadness": "sad"}  # EmoDB -> model
VOICES = {"slt": "female", "kal16": "male", "awb": "male", "rms": "male"}
PAUSE_S = (2.5, 3.5)
NOISE_FLOOR_DBFS = -66.0


def emodb_items() -> list[dict[str, Any]]:
    rows = (DATA / "emodb" / "manifest.tsv").read_text().splitlines()
    header = rows[0].split("\t")
    items = []
    for row in rows[1:]:
        fields = dict(zip(header, row.split("\t"), strict=True))
        if fields["emotion"] in EMOTIONS:
            items.append({"kind": "emodb", "clip": str(DATA / "emodb" / fields["path"]), "text": "",
                          "emotion": EMOTIONS[fields["emotion"]], "gender": fields["gender"],
                          "speaker": fields["speaker"]})
    return items


def robocup_items() -> list[dict[str, Any]]:
    items: list[dict[str, Any]] = []
    for line in (DATA / "robocup" / "questions.tsv").read_text(encoding="utf-8").splitlines():
        fields = line.split("\t")
        if len(fields) >= 3 and fields[0].strip().isdigit():
            items.extend({"kind": "robocup", "say": fields[1].strip(), "text": fields[1].strip(), "voice": voice,
                          "emotion": "", "gender": gender, "speaker": voice} for voice, gender in VOICES.items())
    return items


def render_utterance(item: dict[str, Any], array: str, azimuth_deg: float, distance_m: float
                     ) -> tuple[np.ndarray, float, float]:
    """(samples, mics) float at the source's own peak level, and its speech span in seconds."""
    from esiaf.scenes import Scene, SpeechSource, read_clip, render_parts, speak
    clip = read_clip(item["clip"], RATE_HZ) if "clip" in item else speak(item["say"], item["voice"], RATE_HZ)
    source = SpeechSource(azimuth_deg=azimuth_deg, distance_m=distance_m, clip=item.get("clip", ""),
                          say=item.get("say", ""), voice=item.get("voice", "slt"))
    scene = Scene(array=array, speech=[source], tail_s=0.3, peak_dbfs=0.0)
    speech, _, truth = render_parts(scene)
    level = float(np.max(np.abs(clip)))  # render_parts scales to full scale: back to the clip's own peak
    utterance = truth["utterances"][0]
    return speech * level * 0.9, utterance["start_s"], utterance["end_s"]


def build(minutes: float, seed: int, array: str, cache: Path | None = None) -> tuple[Path, dict[str, Any]]:
    """The data set's audio (16-bit WAV) and truth, rendered or read from the cache."""
    params = {"minutes": float(minutes), "seed": seed, "array": array, "version": VERSION}
    key = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]
    folder = (cache or Path(tempfile.gettempdir()) / "esiaf-dataset") / f"{array}-{minutes:g}min-{seed}-{key}"
    audio_path, truth_path = folder / "dataset.wav", folder / "dataset.json"
    if audio_path.exists() and truth_path.exists():
        print(f"dataset: cached {audio_path}", file=sys.stderr, flush=True)
        return audio_path, json.loads(truth_path.read_text())
    import soundfile

    from esiaf.arrays import load_array
    rng = np.random.default_rng(seed)
    pool = emodb_items() + robocup_items()
    kinds = {"emodb": [i for i in pool if i["kind"] == "emodb"], "robocup": [i for i in pool if i["kind"] == "robocup"]}
    total = int(minutes * 60 * RATE_HZ)
    mics = len(load_array(array).positions_m.T)
    noise_rms = 10 ** (NOISE_FLOOR_DBFS / 20)
    mix = (rng.standard_normal((total, mics), dtype=np.float32) * noise_rms)
    utterances: list[dict[str, Any]] = []
    at_s, started = float(rng.uniform(*PAUSE_S)), time.monotonic()
    while True:
        kind = "emodb" if rng.random() < 0.5 else "robocup"
        item = kinds[kind][int(rng.integers(len(kinds[kind])))]
        azimuth, distance = float(rng.uniform(0, 360)), float(rng.uniform(1.0, 2.0))
        speech, start_s, end_s = render_utterance(item, array, azimuth, distance)
        at = int(at_s * RATE_HZ)
        if at + len(speech) > total:
            break
        mix[at:at + len(speech)] += speech.astype(np.float32)
        utterances.append({**{k: v for k, v in item.items() if k not in ("say",)}, "azimuth_deg": round(azimuth, 2),
                           "distance_m": round(distance, 3), "start_s": round(at_s + start_s, 4),
                           "end_s": round(at_s + end_s, 4)})
        at_s += len(speech) / RATE_HZ + float(rng.uniform(*PAUSE_S))
        if len(utterances) % 50 == 0:
            print(f"dataset: rendered {len(utterances)} utterances, {at_s / 60:.1f} of {minutes:g} min "
                  f"in {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
    folder.mkdir(parents=True, exist_ok=True)
    ints = np.round(np.clip(mix, -1, 1 - 1 / 32768) * 32768).astype(np.int16)
    soundfile.write(str(audio_path.with_suffix(".part.wav")), ints, RATE_HZ, subtype="PCM_16")
    truth = {**params, "sample_rate_hz": RATE_HZ, "duration_s": total / RATE_HZ, "channels": mics,
             "speech_s": round(sum(u["end_s"] - u["start_s"] for u in utterances), 1), "utterances": utterances}
    truth_path.write_text(json.dumps(truth, indent=1) + "\n")
    audio_path.with_suffix(".part.wav").rename(audio_path)  # the audio last: a cache entry is complete or absent
    print(f"dataset: wrote {audio_path} ({len(utterances)} utterances, {minutes:g} min) in "
          f"{time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
    return audio_path, truth

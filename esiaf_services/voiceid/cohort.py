"""Cohort speech for score normalisation: voices that are none of the enrolled (nor EmoDB's).

Real speech from the shared data folder (CMU ARCTIC, the pocketsphinx test recordings:
LibriVox, cards, forever, digits) and, optionally, Debian's flite voices reading RoboCup
questions. Every clip is cut to its speech span, like a VAD segment, and clips under 1 s are
left out (the voiceid judges nothing shorter).
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import soundfile

from esiaf.scenes import speech_bounds

REAL_SPEECH = ("speech/cmu_arctic/*.wav", "speech/pocketsphinx/librivox/*.wav", "speech/pocketsphinx/cards/*.wav",
               "speech/pocketsphinx/forever/*.wav", "speech/pocketsphinx/*.raw")
FLITE_VOICES = ("slt", "kal16", "awb", "rms")  # 16 kHz voices (kal is 8 kHz)
MIN_SECONDS = 1.0


def _speech(samples: np.ndarray) -> np.ndarray | None:
    first, last = speech_bounds(samples)
    span = samples[first:last].astype(np.float32)
    return span if span.size >= MIN_SECONDS * 16000 else None


def real_clips(shared_data: Path) -> list[tuple[str, np.ndarray]]:
    """(name, 16 kHz speech span) of the shared data's real, non-EmoDB speech."""
    out = []
    for pattern in REAL_SPEECH:
        for path in sorted(shared_data.glob(pattern)):
            if path.suffix == ".raw":  # headerless s16le, 16 kHz mono
                samples = np.fromfile(path, "<i2").astype(np.float32) / 32768.0
            else:
                samples, rate = soundfile.read(path, dtype="float32")
                if rate != 16000 or samples.ndim != 1:
                    continue
            span = _speech(samples)
            if span is not None:
                out.append((str(path.relative_to(shared_data)), span))
    return out


def flite_clips(sentences: list[str], voices: tuple[str, ...] = FLITE_VOICES) -> list[tuple[str, np.ndarray]]:
    """(name, speech span) of each flite voice reading each sentence; nothing without flite."""
    if not shutil.which("flite"):
        return []
    out = []
    with tempfile.TemporaryDirectory(prefix="esiaf-cohort-") as folder:
        wav = Path(folder) / "out.wav"
        for voice in voices:
            for n, sentence in enumerate(sentences):
                subprocess.run(["flite", "-voice", voice, "-t", sentence, "-o", str(wav)], check=True,
                               capture_output=True, timeout=60)
                samples, rate = soundfile.read(wav, dtype="float32")
                span = _speech(samples) if rate == 16000 else None
                if span is not None:
                    out.append((f"flite-{voice}-{n}", span))
    return out


def robocup_questions(shared_data: Path, count: int) -> list[str]:
    """The first ``count`` RoboCup@Home questions (``robocup/questions.tsv``)."""
    rows = [line.split("\t") for line in (shared_data / "robocup" / "questions.tsv").read_text().splitlines()
            if line and not line.startswith("#")]
    return [row[1] for row in rows[:count]]

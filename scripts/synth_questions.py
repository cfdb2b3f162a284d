"""Synthesise sentences with Debian's flite into one 16 kHz mono WAV plus a JSON truth file.

Examples (from the repository root)::

    python scripts/synth_questions.py --indices 15,32,42 --out /tmp/q.wav
    python scripts/synth_questions.py --count 50 --voice kal16 --out /tmp/all.wav
    python scripts/synth_questions.py --sentence "go forward ten meters" --out /tmp/go.wav

The WAV holds ``lead_in_s`` of silence, each sentence's flite waveform separated by ``gap_s`` of silence,
then ``tail_s`` of silence.  Next to it, ``<name>.json`` gives per sentence ``{index, text, start_s,
end_s}``, where start and end bound the speech: flite's own quiet lead and tail (samples with
|x| <= 1 % of full scale) are excluded from the bounds but kept in the audio.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import tempfile
import wave
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

LOGGER = logging.getLogger(__name__)

SAMPLE_RATE_HZ = 16000
FULL_SCALE = 32768.0
SPEECH_THRESHOLD_FRACTION = 0.01
REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_QUESTIONS = REPO_ROOT.parent / "shared" / "data" / "robocup" / "questions.tsv"
FLITE_MISSING = "flite not found: install Debian's flite (apt-get install flite)"


class SynthesisError(RuntimeError):
    """flite or sox is missing or failed, or the input is unusable."""


@dataclass(frozen=True)
class SentenceTruth:
    index: int
    text: str
    start_s: float
    end_s: float


def available_voices() -> list[str]:
    """Voices compiled into the installed flite (``flite -lv``)."""
    output = _run(["flite", "-lv"]).decode()
    return output.split(":", 1)[1].split() if ":" in output else output.split()


def synthesise_sentence(text: str, voice: str = "slt") -> np.ndarray:
    """One sentence as int16 mono samples at 16 kHz (resampled with sox if the voice is not 16 kHz)."""
    if voice not in available_voices():
        raise SynthesisError(f"flite has no voice {voice!r}; available: {', '.join(available_voices())}")
    with tempfile.TemporaryDirectory(prefix="synth-") as folder:
        raw_path = Path(folder) / "flite.wav"
        _run(["flite", "-voice", voice, "-t", text, "-o", str(raw_path)])
        with wave.open(str(raw_path), "rb") as reader:
            rate_hz, channels, width = reader.getframerate(), reader.getnchannels(), reader.getsampwidth()
        if (rate_hz, channels, width) != (SAMPLE_RATE_HZ, 1, 2):
            LOGGER.debug("resampling flite's %d Hz, %d channel output with sox", rate_hz, channels)
            converted_path = Path(folder) / "converted.wav"
            if shutil.which("sox") is None:
                raise SynthesisError(f"voice {voice!r} gives {rate_hz} Hz audio; resampling it needs sox: "
                                     "install Debian's sox (apt-get install sox)")
            _run(["sox", str(raw_path), "-r", str(SAMPLE_RATE_HZ), "-c", "1", "-b", "16",
                  "-e", "signed-integer", str(converted_path)])
            raw_path = converted_path
        with wave.open(str(raw_path), "rb") as reader:
            samples = np.frombuffer(reader.readframes(reader.getnframes()), dtype="<i2")
    if not np.any(np.abs(samples.astype(np.int32)) > SPEECH_THRESHOLD_FRACTION * FULL_SCALE):
        raise SynthesisError(f"flite produced no audible speech for {text!r}")
    return samples


def speech_bounds(samples: np.ndarray) -> tuple[int, int]:
    """First and one-past-last sample whose magnitude exceeds 1 % of full scale."""
    loud = np.flatnonzero(np.abs(samples.astype(np.int32)) > SPEECH_THRESHOLD_FRACTION * FULL_SCALE)
    return int(loud[0]), int(loud[-1]) + 1


def synthesise_to_wav(sentences: list[tuple[int, str]], out_path: Path, voice: str = "slt",
                      lead_in_s: float = 1.0, gap_s: float = 2.5, tail_s: float = 1.0) -> list[SentenceTruth]:
    """Write ``sentences`` ((index, text) pairs) to ``out_path`` and the truth to ``out_path`` with .json."""
    if not sentences:
        raise SynthesisError("no sentences to synthesise")
    if min(lead_in_s, gap_s, tail_s) < 0:
        raise SynthesisError("silences must not be negative")
    pieces = [np.zeros(round(lead_in_s * SAMPLE_RATE_HZ), dtype="<i2")]
    position = len(pieces[0])
    truths = []
    for number, (index, text) in enumerate(sentences):
        if number:
            pieces.append(np.zeros(round(gap_s * SAMPLE_RATE_HZ), dtype="<i2"))
            position += len(pieces[-1])
        samples = synthesise_sentence(text, voice)
        first, last = speech_bounds(samples)
        truths.append(SentenceTruth(index=index, text=text,
                                    start_s=round((position + first) / SAMPLE_RATE_HZ, 4),
                                    end_s=round((position + last) / SAMPLE_RATE_HZ, 4)))
        pieces.append(samples)
        position += len(samples)
    pieces.append(np.zeros(round(tail_s * SAMPLE_RATE_HZ), dtype="<i2"))
    audio = np.concatenate(pieces).astype("<i2")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with wave.open(str(out_path), "wb") as writer:
        writer.setnchannels(1)
        writer.setsampwidth(2)
        writer.setframerate(SAMPLE_RATE_HZ)
        writer.writeframes(audio.tobytes())
    truth = {"wav": out_path.name, "sample_rate_hz": SAMPLE_RATE_HZ, "voice": voice,
             "duration_s": round(len(audio) / SAMPLE_RATE_HZ, 4), "sentences": [asdict(t) for t in truths]}
    out_path.with_suffix(".json").write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")
    return truths


def read_questions(path: Path) -> dict[int, str]:
    """index -> question from ``index<TAB>question<TAB>answer`` lines; ``#`` lines are comments."""
    questions = {}
    for line_number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split("\t")
        if len(fields) < 2 or not fields[0].strip().isdigit():
            raise SynthesisError(f"{path}:{line_number}: expected index<TAB>question<TAB>answer")
        questions[int(fields[0])] = fields[1].strip()
    return questions


def _run(arguments: list[str]) -> bytes:
    if shutil.which(arguments[0]) is None:
        raise SynthesisError(FLITE_MISSING if arguments[0] == "flite" else f"{arguments[0]} not found")
    completed = subprocess.run(arguments, capture_output=True, check=False)
    if completed.returncode != 0:
        complaint = completed.stderr.decode(errors="replace").strip()
        raise SynthesisError(f"{arguments[0]} failed ({completed.returncode}): {complaint}")
    return completed.stdout


def _select(arguments: argparse.Namespace) -> list[tuple[int, str]]:
    if arguments.sentence:
        return list(enumerate(arguments.sentence, start=1))
    questions = read_questions(arguments.questions)
    if arguments.indices:
        try:
            indices = [int(part) for part in arguments.indices.split(",") if part.strip()]
        except ValueError as error:
            raise SynthesisError(f"--indices must be integers separated by commas: {arguments.indices!r}") \
                from error
        unknown = [index for index in indices if index not in questions]
        if unknown:
            raise SynthesisError(f"no questions with indices {unknown} in {arguments.questions}")
        return [(index, questions[index]) for index in indices]
    return sorted(questions.items())[:arguments.count]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--questions", type=Path, default=DEFAULT_QUESTIONS,
                        help=f"index<TAB>question<TAB>answer file (default {DEFAULT_QUESTIONS})")
    choice = parser.add_mutually_exclusive_group(required=True)
    choice.add_argument("--indices", help="question indices, e.g. 1,5,9")
    choice.add_argument("--count", type=int, help="the first N questions")
    choice.add_argument("--sentence", action="append", help="a sentence to speak (repeatable)")
    parser.add_argument("--voice", default="slt", help="flite voice: slt (default), kal16, awb, rms, ...")
    parser.add_argument("--lead-in-s", type=float, default=1.0, help="silence before the first sentence")
    parser.add_argument("--gap-s", type=float, default=2.5, help="silence between sentences")
    parser.add_argument("--tail-s", type=float, default=1.0, help="silence after the last sentence")
    parser.add_argument("--out", type=Path, required=True,
                        help="WAV to write; the truth goes to the .json beside it")
    arguments = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        truths = synthesise_to_wav(_select(arguments), arguments.out, arguments.voice,
                                   arguments.lead_in_s, arguments.gap_s, arguments.tail_s)
    except (OSError, SynthesisError) as error:
        LOGGER.error("error: %s", error)
        return 1
    LOGGER.info("wrote %s and %s (%d sentences)", arguments.out, arguments.out.with_suffix(".json").name,
                len(truths))
    return 0


if __name__ == "__main__":
    sys.exit(main())

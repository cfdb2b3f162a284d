"""Measure the recogniser on the RoboCup questions spoken by flite voices.

Run from the repository root::

    python -m esiaf_services.asr.tools.benchmark_robocup [--voices slt,kal16] [--questions FILE]

For each voice, every question is synthesised with flite (``scripts/synth_questions.py``) and decoded
with the RoboCup grammar twice: whole (``recognise()``, which reports accuracy, decode time and
real-time factor) and streamed in 20 ms chunks (``start``/``feed``/``finish``, which reports accuracy
and the latency of ``finish()``).  A question counts as right when the best text equals the
normalised question exactly.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import statistics
import sys
import time
from pathlib import Path
from types import ModuleType

from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR, normalise_sentence, read_questions
from esiaf_services.asr.recognizer import PocketsphinxRecognizer

LOGGER = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_QUESTIONS_TSV = REPO_ROOT.parent / "shared" / "data" / "robocup" / "questions.tsv"
CHUNK_S = 0.020


def load_synthesiser() -> ModuleType:
    """``scripts/synth_questions.py`` as a module (``scripts`` is not a package)."""
    path = REPO_ROOT / "scripts" / "synth_questions.py"
    spec = importlib.util.spec_from_file_location("synth_questions", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def best_text(hypotheses: list) -> str:
    return hypotheses[0].text if hypotheses else ""


def benchmark_voice(voice: str, questions: list[tuple[int, str]], synthesiser: ModuleType) -> None:
    """Decode every question whole with one recogniser and streamed with another (fresh for the voice,
    so its live cepstral mean normalisation starts from pocketsphinx's default, as in the service)."""
    recogniser = PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR)
    streaming_recogniser = PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR)
    chunk_bytes = round(CHUNK_S * recogniser.sample_rate_hz) * 2
    whole_right = streamed_right = 0
    decode_s: list[float] = []
    audio_s: list[float] = []
    finish_ms: list[float] = []
    for index, question in questions:
        pcm = synthesiser.synthesise_sentence(question, voice).tobytes()
        expected = normalise_sentence(question)
        started = time.perf_counter()
        hypotheses = recogniser.recognise(pcm)
        decode_s.append(time.perf_counter() - started)
        audio_s.append(len(pcm) / 2 / recogniser.sample_rate_hz)
        whole_right += best_text(hypotheses) == expected
        if best_text(hypotheses) != expected:
            LOGGER.info("%s #%d wrong: %r (expected %r)", voice, index, best_text(hypotheses), expected)
        streaming_recogniser.start()
        for offset in range(0, len(pcm), chunk_bytes):
            streaming_recogniser.feed(pcm[offset:offset + chunk_bytes])
        started = time.perf_counter()
        streamed = streaming_recogniser.finish()
        finish_ms.append((time.perf_counter() - started) * 1000)
        streamed_right += best_text(streamed) == expected
        if best_text(streamed) != expected:
            LOGGER.info("%s #%d streamed wrong: %r", voice, index, best_text(streamed))
    count = len(questions)
    LOGGER.info("%s: whole %d/%d exact, %.1f ms per utterance (%.2f s audio), real-time factor %.3f; "
                "streamed %d/%d exact, finish() median %.2f ms (max %.2f ms)",
                voice, whole_right, count, 1000 * statistics.mean(decode_s), statistics.mean(audio_s),
                sum(decode_s) / sum(audio_s), streamed_right, count, statistics.median(finish_ms),
                max(finish_ms))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--voices", default="slt,kal16", help="comma-separated flite voices")
    parser.add_argument("--questions", type=Path, default=DEFAULT_QUESTIONS_TSV)
    arguments = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    questions = read_questions(arguments.questions)
    synthesiser = load_synthesiser()
    started = time.perf_counter()
    PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR)
    LOGGER.info("recogniser with grammar loaded in %.2f s", time.perf_counter() - started)
    for voice in arguments.voices.split(","):
        benchmark_voice(voice.strip(), questions, synthesiser)
    return 0


if __name__ == "__main__":
    sys.exit(main())

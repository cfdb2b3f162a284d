"""Utterance features: openSMILE functionals (eGeMAPS v02 or ComParE 2016) of a whole segment.

The same code serves training (``tools/train.py``) and the running service, so a model sees
features computed exactly as it was trained on, over the same stretch of audio: the speech span
as the VAD's segmenter finds it, without the pre-roll and hang-over the VAD forwards around it
(``speech_span``; the models are trained on the spans of both VAD backends). Functionals are
averages over every frame, so half a second of silence more or less changes them enough to flip
the label (tried: padding 40 EmoDB utterances with the VAD's 650 ms of silence took a 4-class
model's accuracy on them from 0.85 to 0.50).
"""
from __future__ import annotations

import functools
from typing import Any

import numpy as np

from esiaf.features import SharedExtractor, shared
from services.vad.segmenter import ProbabilityParams, ProbabilitySegmenter, Segmenter, SegmenterParams, level_db

FEATURE_SETS = ("eGeMAPSv02", "ComParE_2016")


class FeatureError(Exception):
    """Unknown feature set, or audio the extractor cannot use."""


class FeatureExtractor:
    """openSMILE functionals over a whole utterance: float32 vector of a fixed length."""

    def __init__(self, feature_set: str, sample_rate_hz: int = 16000):
        if feature_set not in FEATURE_SETS:
            raise FeatureError(f"unknown feature set {feature_set!r}; known: {', '.join(FEATURE_SETS)}")
        try:
            import opensmile
        except ImportError:
            raise FeatureError("the opensmile package is missing: pip install -e '.[emotion]'") from None
        self.feature_set = feature_set
        self.sample_rate_hz = sample_rate_hz
        self._smile = opensmile.Smile(feature_set=getattr(opensmile.FeatureSet, feature_set),
                                      feature_level=opensmile.FeatureLevel.Functionals)
        self.names: list[str] = list(self._smile.feature_names)

    @property
    def size(self) -> int:
        return len(self.names)

    def __call__(self, samples: np.ndarray) -> np.ndarray:
        """``samples``: mono float in [-1, 1] or int16, at ``sample_rate_hz``."""
        if samples.dtype == np.int16:
            samples = samples.astype(np.float32) / 32768.0
        values = self._smile.process_signal(np.asarray(samples, dtype=np.float32), self.sample_rate_hz)
        vector = values.to_numpy(dtype=np.float32).reshape(-1)
        if vector.shape[0] != self.size:
            raise FeatureError(f"{self.feature_set} gave {vector.shape[0]} values, expected {self.size}")
        return np.nan_to_num(vector, nan=0.0, posinf=0.0, neginf=0.0)


def shared_extractor(feature_set: str, sample_rate_hz: int = 16000) -> SharedExtractor[FeatureExtractor]:
    """The process's one :class:`FeatureExtractor` of ``feature_set``: every classifier of this
    process that uses the set gets the same features of an utterance, computed once
    (``esiaf/features.py``); ``.extractor`` is the FeatureExtractor."""
    return shared(f"{feature_set}@{sample_rate_hz}", lambda: FeatureExtractor(feature_set, sample_rate_hz))


VADS = ("silero", "energy")  # the vad service's backends; silero is its default


def speech_span(samples: np.ndarray, sample_rate_hz: int, chunk_ms: float = 20.0,
                vad: str = "silero") -> tuple[int, int]:
    """(first, end) sample of what the vad service (backend ``vad``, default settings) would call
    speech in a recording of one utterance (float samples in [-1, 1]): from the first segment's
    onset to the last segment's end; the whole recording if the VAD would find none. The two
    backends cut differently (Silero's span starts a little before the onset and ends after the
    last speech-like window, the energy segmenter's on its loud chunks), so the bundled models are
    trained on both spans (``tools/train.py``)."""
    if vad not in VADS:
        raise FeatureError(f"unknown VAD {vad!r}; known: {', '.join(VADS)}")
    step = max(1, round(sample_rate_hz * chunk_ms / 1000))
    pad = 0
    if vad == "silero":  # its state starts on half a second of silence, as in a stream between utterances
        pad = sample_rate_hz // 2
        samples = np.concatenate([np.zeros(pad, np.float32), samples, np.zeros(pad, np.float32)])
        segmenter: Any = ProbabilitySegmenter(ProbabilityParams())
        probability = _silero_model().stream(sample_rate_hz).chunk_probability
    else:
        segmenter = Segmenter(SegmenterParams())
    spans = []

    def ns(frames: int) -> int:
        return frames * 1_000_000_000 // sample_rate_hz

    for offset in range(0, len(samples), step):
        chunk = samples[offset:offset + step]
        if vad == "silero":
            score = probability(chunk) if chunk.size else 0.0
        else:
            score = level_db(float(np.max(np.abs(chunk))) if chunk.size else 0.0)
        last = offset + step >= len(samples)
        for forward in segmenter.process(None, ns(offset), ns(offset + len(chunk)), score, force_end=last):
            if forward.ended:
                spans.append(forward.segment)
    length = len(samples) - 2 * pad
    if not spans:
        return 0, length
    first = (spans[0][0] * sample_rate_hz + 999_999_999) // 1_000_000_000 - pad
    end = spans[-1][1] * sample_rate_hz // 1_000_000_000 - pad
    return min(max(0, first), length), min(max(0, end), length)


@functools.cache
def _silero_model():
    from services.vad.silero import SileroModel
    return SileroModel()

"""Utterance features: openSMILE functionals (eGeMAPS v02 or ComParE 2016) of a whole segment.

The same function serves training (``tools/train.py``) and the running service, so a model
always sees features computed exactly as it was trained on.
"""
from __future__ import annotations

import numpy as np

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

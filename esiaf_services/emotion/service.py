"""Emotion service: classifies each VAD segment, as a whole, into an emotion.

:class:`UtteranceClassifier` is an utterance analyser of the SDK (``esiaf.utterance``): for each
segment it asks the configured backend (``backends.py``) for a probability per label. The SDK
collects each stream's segment, and covers audio too short or too quiet to judge with a
"nothing" result, so fusion never waits for a label that will not come.
The gender service is the same component with another result type and model.
"""
from __future__ import annotations

import logging
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from esiaf import SetupError
from esiaf.utterance import UtteranceComponent
from esiaf.utterance import UtteranceSettings as BaseUtteranceSettings
from esiaf_services.emotion.backends import BackendError, Classifier, load_backend

log = logging.getLogger(__name__)


class UtteranceSettings(BaseUtteranceSettings):
    backend: str = "onnx"  # onnx | python (see backends.py)
    model: str = "emotion4"  # bundled model name, an .onnx file, or package.module:Class (python)
    # onnx: label_map, threads; python: the class's keyword arguments
    model_options: dict[str, Any] = Field(default_factory=dict)


class UtteranceClassifier(UtteranceComponent):
    """Base of the emotion and gender services: one label result per VAD segment, from a model."""

    Settings = UtteranceSettings
    settings: UtteranceSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {
        "model": "bundled model name, .onnx file, or package.module:Class for the python backend",
        "backend": "onnx (default) or python"}

    def __init__(self, settings: UtteranceSettings):
        super().__init__(settings)
        self.classifier: Classifier | None = None

    def setup(self) -> None:
        s = self.settings
        try:
            self.classifier = load_backend(s.backend, s.model, s.model_options)
        except BackendError as exc:
            raise SetupError(f"{self.service} model: {exc}") from None
        if self.classifier.sample_rate_hz != s.sample_rate_hz:
            raise SetupError(f"{self.service} model {s.model} takes {self.classifier.sample_rate_hz} Hz audio, "
                             f"the service is set to {s.sample_rate_hz} Hz")
        self.info.update(model=s.model, backend=s.backend, labels=list(self.classifier.labels))
        log.info("model=%s backend=%s labels=%s", s.model, s.backend, ",".join(self.classifier.labels))

    def analyse(self, samples: np.ndarray, rate: int) -> dict[str, Any]:
        assert self.classifier is not None  # setup() loads it
        probabilities = self.classifier.classify(samples)
        label = max(probabilities, key=probabilities.__getitem__)
        return {"label": label, "probability": probabilities[label], "class_probabilities": probabilities}


class Emotion(UtteranceClassifier):
    """Emotion of each speech segment (neutral/angry/happy/sad; 7 EmoDB classes with model emotion7)."""

    service = "emotion"
    kind = "emotion"

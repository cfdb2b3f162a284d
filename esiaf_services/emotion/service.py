"""Emotion service: classifies each VAD segment, as a whole, into an emotion.

An utterance classifier of the SDK (:class:`esiaf.UtteranceClassifier`): for each segment it asks
the configured backend (``esiaf/speech/classifiers.py``) for a probability per label. The SDK collects each
stream's segment, and covers audio too short or too quiet to judge with a "nothing" result, so
fusion never waits for a label that will not come.
"""
from __future__ import annotations

from pathlib import Path

from esiaf import ClassifierSettings, UtteranceClassifier
from esiaf.speech.classifiers import Classifier, load_classifier

MODELS = Path(__file__).resolve().parent / "models"  # the bundled emotion model(s), by name


class EmotionSettings(ClassifierSettings):
    backend: str = "onnx"  # onnx | python (see esiaf/speech/classifiers.py)
    model: str = "emotion4"  # bundled model name, an .onnx file, or package.module:Class (python)



class Emotion(UtteranceClassifier):
    """Emotion of each speech segment (neutral/angry/happy/sad; 7 EmoDB classes with model emotion7)."""

    service = "emotion"
    kind = "emotion"
    Settings = EmotionSettings
    settings: EmotionSettings  # an instance of Settings: its fields, for type checkers

    def load_model(self) -> Classifier:
        s = self.settings
        return load_classifier(self.service, s.backend, s.model, s.model_options, MODELS)

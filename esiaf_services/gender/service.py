"""Gender service: male or female, with a probability, for each VAD segment.

An utterance classifier of the SDK (:class:`esiaf.UtteranceClassifier`) with the gender result
kind and the bundled gender model, loaded by the SDK's label classifiers
(``esiaf/speech/classifiers.py``; the model in ``models/``). ``esiaf run`` starts it as a guest in the emotion
service's process (``esiaf/hosting.py``), where the openSMILE features of each utterance are
computed once for both; alone, ``python -m esiaf_services.gender``.
"""
from __future__ import annotations

from pathlib import Path

from esiaf import ClassifierSettings, UtteranceClassifier
from esiaf.speech.classifiers import Classifier, load_classifier

MODELS = Path(__file__).resolve().parent / "models"  # the bundled gender model(s), by name


class GenderSettings(ClassifierSettings):
    backend: str = "onnx"  # onnx | python (see esiaf/speech/classifiers.py)
    model: str = "gender"  # bundled model name, an .onnx file, or package.module:Class (python)


class Gender(UtteranceClassifier):
    """Speaker gender of each speech segment (male/female)."""

    service = "gender"
    kind = "gender"
    Settings = GenderSettings
    settings: GenderSettings  # an instance of Settings: its fields, for type checkers

    def load_model(self) -> Classifier:
        s = self.settings
        return load_classifier(self.service, s.backend, s.model, s.model_options, MODELS)

"""Gender service: male or female, with a probability, for each VAD segment.

It is the emotion service's component (``esiaf_services/emotion/service.py``) with the gender
result type and the bundled gender model; backends and settings are the same. ``esiaf run``
starts it as a guest in the emotion service's process (``esiaf/hosting.py``), where the openSMILE
features of each utterance are computed once for both; alone, ``python -m esiaf_services.gender``.
"""
from __future__ import annotations

from esiaf_services.emotion.service import UtteranceClassifier, UtteranceSettings


class GenderSettings(UtteranceSettings):
    model: str = "gender"


class Gender(UtteranceClassifier):
    """Speaker gender of each speech segment (male/female)."""

    service = "gender"
    kind = "gender"
    Settings = GenderSettings
    settings: GenderSettings  # an instance of Settings: its fields, for type checkers

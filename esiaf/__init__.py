"""ESIAF: the component SDK of a distributed speech-analysis pipeline for robots.

An analyser is a small class against :class:`esiaf.UtteranceAnalyser` (docs/writing-an-analyser.md);
a component of any other shape, a :class:`esiaf.Processor` or :class:`esiaf.Component`.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# Imported on first use (PEP 562), so that a light module such as esiaf.tools.health (a container's
# healthcheck, run every few seconds) starts without loading numpy, ZeroMQ and pydantic.
_EXPORTS = {
    "Audio": "esiaf.audio", "SampleClock": "esiaf.audio",
    "Component": "esiaf.component", "SetupError": "esiaf.processor", "Processor": "esiaf.processor",
    "Context": "esiaf.node", "Node": "esiaf.node",
    "AudioFormat": "esiaf.formats",
    "hypothesis": "esiaf.results", "ssl_direction": "esiaf.results",
    "main": "esiaf.runner",
    "UtteranceComponent": "esiaf.utterance", "UtteranceSettings": "esiaf.utterance",
    "Utterance": "esiaf.utterance", "UtteranceAnalyser": "esiaf.utterance", "UtteranceClassifier": "esiaf.utterance",
    "ClassifierSettings": "esiaf.utterance",
    "ComponentSettings": "esiaf.settings", "BackendSettings": "esiaf.settings", "SettingsError": "esiaf.settings",
    "load_settings": "esiaf.settings",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:  # `X as X`: re-exported names, for type checkers and linters
    from esiaf.audio import Audio as Audio
    from esiaf.audio import SampleClock as SampleClock
    from esiaf.component import Component as Component
    from esiaf.formats import AudioFormat as AudioFormat
    from esiaf.node import Context as Context
    from esiaf.node import Node as Node
    from esiaf.processor import Processor as Processor
    from esiaf.processor import SetupError as SetupError
    from esiaf.results import hypothesis as hypothesis
    from esiaf.results import ssl_direction as ssl_direction
    from esiaf.runner import main as main
    from esiaf.settings import BackendSettings as BackendSettings
    from esiaf.settings import ComponentSettings as ComponentSettings
    from esiaf.settings import SettingsError as SettingsError
    from esiaf.settings import load_settings as load_settings
    from esiaf.utterance import ClassifierSettings as ClassifierSettings
    from esiaf.utterance import Utterance as Utterance
    from esiaf.utterance import UtteranceAnalyser as UtteranceAnalyser
    from esiaf.utterance import UtteranceClassifier as UtteranceClassifier
    from esiaf.utterance import UtteranceComponent as UtteranceComponent
    from esiaf.utterance import UtteranceSettings as UtteranceSettings


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'esiaf' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value

"""ESIAF: the component SDK of a distributed speech-analysis pipeline for robots.

A component is a small class against :class:`esiaf.Component`; see README.md,
"Writing a component".
"""
from esiaf.audio import Audio, SampleClock
from esiaf.component import Component, SetupError
from esiaf.formats import AudioFormat
from esiaf.results import hypothesis, ssl_direction
from esiaf.runner import main
from esiaf.settings import ComponentSettings, SettingsError, load_settings

__all__ = ["Audio", "AudioFormat", "Component", "ComponentSettings", "SampleClock", "SettingsError",
           "SetupError", "hypothesis", "load_settings", "main", "ssl_direction"]

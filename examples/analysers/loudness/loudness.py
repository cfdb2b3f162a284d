"""Loudness of each utterance: its peak level and its loudest 30 ms, in dB (96 dB = full scale)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from esiaf import Utterance, UtteranceAnalyser, UtteranceSettings

FULL_SCALE_DB = 96.0  # a 16-bit sample at full scale, as the SDK's silence_db counts


def level_db(amplitude: float) -> float:
    """An amplitude in [0, 1] as a level in dB; -inf for digital silence."""
    return FULL_SCALE_DB + 20.0 * math.log10(amplitude) if amplitude > 0 else -math.inf


class LoudnessSettings(UtteranceSettings):
    window_ms: float = 30.0  # the RMS level is taken over windows this long; the loudest one counts


class Loudness(UtteranceAnalyser):
    """Peak level of each utterance, and the RMS level of its loudest window, in dB."""

    service = "loudness"
    kind = "loudness"  # a result kind of its own: stored, fused, aggregated and shown as "loudness 90"
    Settings = LoudnessSettings
    settings: LoudnessSettings  # an instance of Settings: its fields, for type checkers

    def analyse(self, utterance: Utterance) -> dict[str, Any]:
        samples = utterance.samples.astype(np.float64)
        window = max(1, round(utterance.rate * self.settings.window_ms / 1000))
        whole = samples[: samples.size // window * window].reshape(-1, window) if samples.size >= window \
            else samples.reshape(1, -1)
        loudest = float(np.sqrt(np.mean(whole**2, axis=1)).max())
        return {"value": level_db(float(np.max(np.abs(samples)))),
                "attributes": {"rms_db": round(level_db(loudest), 2), "duration_s": round(utterance.duration_s, 3)}}

"""Is there enough speech in this audio to enrol or learn a voice from? A level-based check.

The audio is cut into 25 ms frames (10 ms hop); a frame is active if its level is at least
``ACTIVE_DB`` above the audio's floor (the 10th percentile of the frame levels) and above
``SILENCE_DBFS``. The speech span runs from the first active frame to the last; the estimated SNR
is the mean level of the active frames over the floor. Pure stationary noise has no frame that
far above its floor (no speech); a short word in silence has a short span.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RATE_HZ = 16000
FRAME, HOP = 400, 160
ACTIVE_DB = 15.0  # a frame this far above the floor is speech
SILENCE_DBFS = -60.0  # quieter frames are never speech
FLOOR_PERCENTILE = 10


@dataclass(frozen=True)
class Quality:
    speech_s: float  # first active frame to last
    active_s: float  # active frames only
    snr_db: float  # mean level of the active frames over the floor (0 with none)
    peak_dbfs: float


def measure(samples: np.ndarray) -> Quality:
    """The speech span, active time, SNR and peak of 16 kHz float audio."""
    samples = np.asarray(samples, np.float64)
    peak = float(np.max(np.abs(samples), initial=0.0))
    peak_dbfs = 20 * np.log10(max(peak, 1e-10))
    if samples.size < FRAME:
        return Quality(0.0, 0.0, 0.0, peak_dbfs)
    count = 1 + (samples.size - FRAME) // HOP
    index = np.arange(FRAME)[None, :] + HOP * np.arange(count)[:, None]
    level = 10 * np.log10(np.mean(samples[index] ** 2, axis=1) + 1e-12)
    floor = float(np.percentile(level, FLOOR_PERCENTILE))
    active = np.flatnonzero((level >= floor + ACTIVE_DB) & (level >= SILENCE_DBFS))
    if not active.size:
        return Quality(0.0, 0.0, 0.0, peak_dbfs)
    span_s = ((active[-1] - active[0]) * HOP + FRAME) / RATE_HZ
    snr = float(10 * np.log10(np.mean(10 ** (level[active] / 10))) - floor)
    return Quality(span_s, active.size * HOP / RATE_HZ, snr, peak_dbfs)


def problem(samples: np.ndarray, min_speech_s: float, min_snr_db: float = ACTIVE_DB) -> str | None:
    """Why this audio is not enough speech (one phrase), or None if it is."""
    quality = measure(samples)
    if quality.speech_s == 0.0:
        return (f"no speech found: the level never rises {ACTIVE_DB:.0f} dB above its floor "
                f"(peak {quality.peak_dbfs:.0f} dBFS): silence or steady noise")
    if quality.speech_s < min_speech_s:
        return f"only {quality.speech_s:.2f} s of speech, at least {min_speech_s:.1f} s needed"
    if quality.snr_db < min_snr_db:
        return f"speech {quality.snr_db:.0f} dB over the noise, at least {min_snr_db:.0f} dB needed"
    return None

"""Is there enough speech in this audio to enrol a voice from, or to tell a voice by? A level-based check.

The audio is cut into 25 ms frames (10 ms hop); a frame is active if its level is at least
``ACTIVE_DB`` above the audio's floor (the 10th percentile of the frame levels) and above
``SILENCE_DBFS``. The speech span runs from the first active frame to the last; ``snr_db`` is the
mean level of the active frames over the floor (at least ACTIVE_DB whenever there is speech: it
says how loud the speech is, not how much of it noise hides). ``overall_snr_db`` is the power of the
whole audio over the floor's, ``10 log10((mean - floor) / floor)``: it falls with the noise (white
noise 20, 10, 5 dB under an ARCTIC sentence: 19.7, 10.1, 5.1 dB) and is what the voiceid's quality
gate (:func:`voice_problem`) uses. Pure stationary noise has no frame far above its floor (no
speech); a short word in silence has a short span.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RATE_HZ = 16000
FRAME, HOP = 400, 160
ACTIVE_DB = 15.0  # a frame this far above the floor is speech
SILENCE_DBFS = -60.0  # quieter frames are never speech
FLOOR_PERCENTILE = 10
MIN_OVERALL_SNR_DB = -30.0  # overall_snr_db of audio whose mean power is (nearly) its floor's


@dataclass(frozen=True)
class Quality:
    speech_s: float  # first active frame to last
    active_s: float  # active frames only
    snr_db: float  # mean level of the active frames over the floor (0 with none)
    peak_dbfs: float
    overall_snr_db: float = 0.0  # mean power of every frame over the floor's (MIN_OVERALL_SNR_DB at worst)


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
    power, floor_power = 10 ** (level / 10), 10 ** (floor / 10)
    over = float(np.mean(power)) / floor_power - 1.0
    overall = max(MIN_OVERALL_SNR_DB, 10 * np.log10(over)) if over > 0 else MIN_OVERALL_SNR_DB
    if not active.size:
        return Quality(0.0, 0.0, 0.0, peak_dbfs, overall)
    span_s = ((active[-1] - active[0]) * HOP + FRAME) / RATE_HZ
    snr = float(10 * np.log10(np.mean(power[active])) - floor)
    return Quality(span_s, active.size * HOP / RATE_HZ, snr, peak_dbfs, overall)


def voice_problem(quality: Quality, min_overall_snr_db: float, min_speech_s: float) -> str | None:
    """Why a segment of this quality cannot tell a voice (one phrase: too noisy by ``overall_snr_db``,
    or too short a speech span), or None if it can. Pure noise is too noisy (its power is near its
    floor's); noisy speech whose frames never rise ACTIVE_DB over the floor has a span of 0 s."""
    if quality.overall_snr_db < min_overall_snr_db:
        return (f"too noisy: {quality.overall_snr_db:.1f} dB over the noise floor, at least "
                f"{min_overall_snr_db:.1f} dB needed")
    if quality.speech_s < min_speech_s:
        return (f"only {quality.speech_s:.2f} s of speech ({ACTIVE_DB:.0f} dB over the floor), at least "
                f"{min_speech_s:.1f} s needed")
    return None


def problem(samples: np.ndarray, min_speech_s: float, min_snr_db: float = ACTIVE_DB) -> str | None:
    """Why this audio is not enough speech to enrol (one phrase), or None if it is."""
    quality = measure(samples)
    if quality.speech_s == 0.0:
        return (f"no speech found: the level never rises {ACTIVE_DB:.0f} dB above its floor "
                f"(peak {quality.peak_dbfs:.0f} dBFS): silence or steady noise")
    if quality.speech_s < min_speech_s:
        return f"only {quality.speech_s:.2f} s of speech, at least {min_speech_s:.1f} s needed"
    if quality.snr_db < min_snr_db:
        return f"speech {quality.snr_db:.0f} dB over the noise, at least {min_snr_db:.0f} dB needed"
    return None

"""Perturbed copies of an enrolment utterance, to enrol a voice as it may also sound.

- ``speed_perturbed``: played faster or slower, tempo and pitch together (Kaldi-style speed
  perturbation, by resampling with soxr);
- ``tilted``: the spectral tilt of more or less vocal effort: a first-order pre-emphasis
  ``y[n] = x[n] - a x[n-1]`` (``a > 0``: louder, brighter speech) or a one-pole low-pass
  ``y[n] = x[n] + |a| y[n-1]`` (``a < 0``: softer, darker), rescaled to the input's RMS.
"""
from __future__ import annotations

import numpy as np

SAMPLE_RATE_HZ = 16000


def speed_perturbed(samples: np.ndarray, factor: float) -> np.ndarray:
    """The utterance played ``factor`` times faster, still at 16 kHz."""
    import soxr
    if factor <= 0:
        raise ValueError(f"speed factor {factor} is not positive")
    if factor == 1:
        return np.asarray(samples, np.float32)
    return soxr.resample(np.asarray(samples, np.float32), SAMPLE_RATE_HZ * factor, SAMPLE_RATE_HZ).astype(np.float32)


def tilted(samples: np.ndarray, coefficient: float) -> np.ndarray:
    """Pre-emphasis (``coefficient`` in (0, 1)) or one-pole low-pass (in (-1, 0)), same RMS."""
    from scipy.signal import lfilter
    if not -1 < coefficient < 1:
        raise ValueError(f"tilt coefficient {coefficient} is outside (-1, 1)")
    x = np.asarray(samples, np.float64)
    if coefficient >= 0:
        y = lfilter([1.0, -coefficient], [1.0], x)
    else:
        y = lfilter([1.0], [1.0, coefficient], x)
    rms_in, rms_out = np.sqrt(np.mean(x ** 2)), np.sqrt(np.mean(y ** 2))
    return (y * (rms_in / rms_out if rms_out > 0 else 0.0)).astype(np.float32)

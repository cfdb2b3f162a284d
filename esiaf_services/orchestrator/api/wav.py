"""Reading a WAV file sent to the API (a voice to enrol, a sound for the robot to play): any rate, integer
or float samples, checked, as mono float samples; a file that is not one is a 422 with the reason."""
from __future__ import annotations

import io
import struct
from math import gcd

import numpy as np
from fastapi import HTTPException

MIN_RATE_HZ, MAX_RATE_HZ = 8_000, 192_000  # as an audio message's (esiaf/receiving.py)


def read_wav(data: bytes, max_channels: int = 64, max_s: float | None = None) -> tuple[int, np.ndarray]:
    """(rate, mono float32 samples, full scale 1) of a WAV file's bytes; HTTPException 422 if unreadable, of
    more than ``max_channels`` channels, of a rate outside 8–192 kHz, longer than ``max_s``, or holding
    samples that are not finite numbers. Checked before any conversion: a header saying 1 Hz must not
    make gigabytes of audio at the rate it is converted to."""
    from scipy.io import wavfile
    try:
        rate_hz, samples = wavfile.read(io.BytesIO(data))
    # what scipy's reader raises for a header cut short (struct.error), 0 channels or 0 bits per sample
    # (ZeroDivisionError), fields that do not add up (ValueError), data cut short (EOFError)
    except (ValueError, EOFError, struct.error, ZeroDivisionError, OverflowError) as exc:
        raise HTTPException(422, f"audio is not a readable WAV file: {exc}") from None
    channels = 1 if samples.ndim == 1 else samples.shape[1]
    if channels > max_channels:
        raise HTTPException(422, f"audio has {channels} channels; at most {max_channels} are taken (mixed down)")
    if not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise HTTPException(422, f"audio at {rate_hz} Hz: {MIN_RATE_HZ}-{MAX_RATE_HZ} Hz are taken")
    if max_s is not None and samples.shape[0] / rate_hz > max_s:
        raise HTTPException(422, f"audio of {samples.shape[0] / rate_hz:.1f} s: at most {max_s:g} s are taken")
    if samples.dtype.kind in "iu":
        info = np.iinfo(samples.dtype)
        samples = (samples.astype(np.float64) - (info.max + info.min + 1) / 2) / (info.max + 1)
    elif not np.all(np.isfinite(samples)):
        raise HTTPException(422, "audio holds samples that are not finite numbers (NaN or infinity)")
    samples = samples.astype(np.float32)
    if samples.ndim == 2:
        samples = samples.mean(axis=1)
    return int(rate_hz), samples


def resample(samples: np.ndarray, rate_hz: int, to_rate_hz: int) -> np.ndarray:
    """``samples`` at ``to_rate_hz`` (float32)."""
    from scipy.signal import resample_poly
    if rate_hz == to_rate_hz:
        return samples
    divisor = gcd(int(rate_hz), to_rate_hz)
    return resample_poly(samples, to_rate_hz // divisor, int(rate_hz) // divisor).astype(np.float32)

"""Perturbed copies of an enrolment utterance, to enrol a voice as it may also sound.

The orchestrator's WAV enrolment adds :func:`room_copies` of each WAV beside its clean embedding
(multi-condition enrolment); bench/voiceid.py measures them (``--room-enrolment``) and the other
perturbations (``--variants``).

- ``speed_perturbed``: played faster or slower, tempo and pitch together (Kaldi-style speed
  perturbation, by resampling with soxr);
- ``tilted``: the spectral tilt of more or less vocal effort: a first-order pre-emphasis
  ``y[n] = x[n] - a x[n-1]`` (``a > 0``: louder, brighter speech) or a one-pole low-pass
  ``y[n] = x[n] + |a| y[n-1]`` (``a < 0``: softer, darker), rescaled to the input's RMS;
- ``reverberant``: through a simulated room (pyroomacoustics) with pink noise, to enrol from a
  clean WAV a voice that will be heard across a room;
- ``room_copies``: the first ``count`` of ``ROOMS``, each through :func:`reverberant` with its own
  seed: deterministic, the same WAV gives the same copies.

The noise is pink Gaussian noise made here from a seeded generator: nothing is read or downloaded,
and it is not the kitchen noise (shared/data) of the benchmark's test room, nor are the rooms that
room (RT60 0.4 s, 6 × 5 × 3 m, 1.5 m): the copies are not fitted to the trials they are measured on.
"""
from __future__ import annotations

from functools import lru_cache

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
    y = lfilter([1.0, -coefficient], [1.0], x) if coefficient >= 0 else lfilter([1.0], [1.0, coefficient], x)
    rms_in, rms_out = np.sqrt(np.mean(x ** 2)), np.sqrt(np.mean(y ** 2))
    return (y * (rms_in / rms_out if rms_out > 0 else 0.0)).astype(np.float32)


def pink_noise(n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise whose power falls as 1/f (shaped in the frequency domain), unit RMS."""
    bins = n_samples // 2 + 1
    spectrum = rng.normal(size=bins) + 1j * rng.normal(size=bins)
    spectrum /= np.sqrt(np.maximum(np.arange(bins), 1.0))
    noise = np.fft.irfft(spectrum, n_samples)
    return noise / np.sqrt(np.mean(noise ** 2))


@lru_cache(maxsize=8)
def _room_response(rt60_s: float, room_m: tuple[float, float, float], distance_m: float) -> np.ndarray:
    import pyroomacoustics as pra
    size = np.array(room_m)
    absorption, max_order = pra.inverse_sabine(rt60_s, size)
    room = pra.ShoeBox(size, fs=SAMPLE_RATE_HZ, materials=pra.Material(absorption), max_order=max_order)
    mic = np.array([size[0] / 2, size[1] / 2, 1.2])
    room.add_microphone(mic)
    room.add_source(mic + np.array([distance_m, 0.0, 0.3]))  # numpy: elementwise
    room.compute_rir()
    return np.asarray(room.rir[0][0], np.float64)


def reverberant(samples: np.ndarray, rt60_s: float, room_m: tuple[float, float, float], distance_m: float,
                snr_db: float, seed: int = 0) -> np.ndarray:
    """The utterance as heard ``distance_m`` from the speaker in a shoebox room (pyroomacoustics,
    mic in the middle at 1.2 m), with pink noise ``snr_db`` below it; 0.1 s of reverberant tail kept."""
    from scipy.signal import fftconvolve
    x = np.asarray(samples, np.float64)
    speech = fftconvolve(x, _room_response(rt60_s, tuple(room_m), distance_m))[:x.size + SAMPLE_RATE_HZ // 10]
    noise = pink_noise(speech.size, np.random.default_rng(seed))
    gain = np.sqrt(np.mean(speech ** 2) / 10 ** (snr_db / 10))
    return (speech + gain * noise).astype(np.float32)


# the rooms of the copies, in the order they are taken: (RT60 s, room m, distance m, pink noise SNR dB);
# the first two are the WAV enrolment's default (bench/voiceid.py --room-enrolment, docs/benchmarks.md:
# d-vector, room trials, all emotions: clean enrolment 35.4 %, + 2 copies 43.8 %, + 4 copies 42.0 %)
ROOMS: tuple[tuple[float, tuple[float, float, float], float, float], ...] = (
    (0.3, (4.0, 5.0, 2.8), 1.0, 20.0), (0.6, (7.0, 6.0, 3.0), 2.0, 5.0),
    (0.5, (5.0, 4.0, 2.7), 1.2, 10.0), (0.8, (8.0, 7.0, 3.2), 2.5, 0.0))


def room_copies(samples: np.ndarray, count: int) -> list[np.ndarray]:
    """The utterance through the first ``count`` rooms of ROOMS (copy n with noise seed n)."""
    if not 0 <= count <= len(ROOMS):
        raise ValueError(f"{count} room copies: 0 to {len(ROOMS)}")
    return [reverberant(samples, *room, seed=n) for n, room in enumerate(ROOMS[:count])]

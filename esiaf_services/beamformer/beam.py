"""Fixed and adaptive beamforming in the STFT domain: delay-and-sum and MVDR, steered by azimuth.

Frames of ``nfft`` samples, hop ``nfft/2``, a square-root Hann window for analysis and synthesis
(their product, a Hann window, sums to one at half overlap: without steering the output is the
reference microphone, delayed by ``nfft - hop`` samples, which :class:`BeamStream` removes so that
its output sample i is the enhanced input sample i).

Far field: a plane wave from azimuth θ (elevation 0) reaches microphone m at position p earlier
than the array's origin by p·u/c, so its steering vector is ``d_m(f) = exp(j 2π f p_m·u / c)``,
normalised to the reference microphone. Weights per frequency bin:

- ``das`` (delay and sum): ``w = d / M``;
- ``mvdr`` (minimum variance distortionless response): ``w = R⁻¹d / (dᴴR⁻¹d)``, where R is the
  noise's spatial covariance, averaged (``noise_smoothing`` per frame) over the frames the caller
  marks as noise (the talker silent), with diagonal loading (``loading`` × the mean of R's
  diagonal) so that a few snapshots or a little leaked speech cannot make it cancel the talker.
  Until noise has been heard, R is the identity and MVDR equals delay-and-sum.

Either way the talker's component passes undistorted (as at the reference microphone). When the
steering changes (a new talker, a talker found or lost), the output of the old and the new
weights is cross-faded over ``crossfade_frames`` frames, so there are no clicks. With no target
the reference microphone passes unchanged.
"""
from __future__ import annotations

import math

import numpy as np

from esiaf.arrays import ArrayGeometry

SPEED_OF_SOUND_M_S = 343.0
METHODS = ("mvdr", "das")


class BeamformerError(ValueError):
    """A configuration the beamformer cannot work with; the message says why."""


class BeamCore:
    """What every stream shares: geometry, window, frequencies."""

    def __init__(self, array: ArrayGeometry, sample_rate_hz: int, *, method: str = "mvdr", nfft: int = 512,
                 reference_mic: int = 0, loading: float = 0.001, noise_smoothing: float = 0.98,
                 crossfade_frames: int = 4):
        if method not in METHODS:
            raise BeamformerError(f"unknown beamforming method {method!r}; known: {', '.join(METHODS)}")
        if array.mics < 2 or array.aperture_m <= 0:
            raise BeamformerError(f"beamforming needs at least two microphones at distinct positions; "
                                  f"{array.describe()} has not")
        if nfft < 64 or nfft & (nfft - 1):
            raise BeamformerError(f"nfft must be a power of two of at least 64, not {nfft}")
        if not 0 <= reference_mic < array.mics:
            raise BeamformerError(f"reference_mic must be from 0 to {array.mics - 1}, not {reference_mic}")
        if not 0 <= noise_smoothing < 1 or loading < 0 or crossfade_frames < 1:
            raise BeamformerError("need 0 <= noise_smoothing < 1, loading >= 0 and crossfade_frames >= 1")
        self.array, self.rate, self.method, self.nfft, self.hop = array, sample_rate_hz, method, nfft, nfft // 2
        self.reference, self.loading, self.smoothing, self.crossfade = reference_mic, loading, noise_smoothing, \
            crossfade_frames
        n = np.arange(nfft)
        self.window = np.sqrt(0.5 - 0.5 * np.cos(2 * np.pi * n / nfft))  # periodic: sums to 1 squared at hop N/2
        self.freqs = np.fft.rfftfreq(nfft, 1 / sample_rate_hz)

    def steering(self, azimuth_deg: float) -> np.ndarray:
        """(bins, mics) steering vectors toward ``azimuth_deg``, 1 at the reference microphone."""
        a = math.radians(azimuth_deg)
        lead_s = self.array.positions_m.T @ np.array([math.cos(a), math.sin(a), 0.0]) / SPEED_OF_SOUND_M_S
        lead_s = lead_s - lead_s[self.reference]
        return np.exp(2j * np.pi * self.freqs[:, None] * lead_s[None, :])

    def stream(self) -> BeamStream:
        return BeamStream(self)


class BeamStream:
    """One stream's beamformer: its samples, noise covariance and steering."""

    def __init__(self, core: BeamCore):
        self.core = core
        mics, bins = core.array.mics, len(core.freqs)
        self.history = np.zeros((core.nfft - core.hop, mics))
        self.pending = np.zeros((0, mics))
        self.ola = np.zeros(core.nfft)
        self.skip = core.nfft - core.hop  # output samples that belong before the stream's start
        self.noise = np.tile(np.eye(mics, dtype=complex), (bins, 1, 1))
        self.noise_frames = 0
        self.target: float | None = None
        self.weights: np.ndarray | None = None  # (bins, mics); None: the reference microphone
        self.previous: np.ndarray | None = None
        self.fade = core.crossfade  # frames into the current cross-fade (done when == crossfade)
        self.frames = 0
        self.fed = self.given = 0  # input samples taken, output samples given

    def steer(self, azimuth_deg: float | None) -> None:
        """Steers at ``azimuth_deg`` from the next frame (None: pass the reference microphone)."""
        if azimuth_deg is None and self.target is None:
            return
        if azimuth_deg is not None and self.target is not None and \
                abs((azimuth_deg - self.target + 180) % 360 - 180) < 1.0:
            return
        self.previous, self.fade = self.weights, 0
        self.target = None if azimuth_deg is None else azimuth_deg % 360.0
        self.weights = None if self.target is None else self._weights()

    def _weights(self) -> np.ndarray:
        assert self.target is not None  # weights are for a direction
        d = self.core.steering(self.target)
        if self.core.method == "das" or self.noise_frames == 0:
            return d / self.core.array.mics
        mics = self.core.array.mics
        diagonal = np.real(np.trace(self.noise, axis1=1, axis2=2)) / mics
        loaded = self.noise + (self.core.loading * diagonal)[:, None, None] * np.eye(mics)
        r_inv_d = np.linalg.solve(loaded, d[:, :, None])[:, :, 0]
        return r_inv_d / np.sum(np.conj(d) * r_inv_d, axis=1, keepdims=True)

    def _apply(self, weights: np.ndarray | None, spectra: np.ndarray) -> np.ndarray:
        if weights is None:
            return spectra[:, self.core.reference]
        return np.sum(np.conj(weights) * spectra, axis=1)

    def process(self, samples: np.ndarray, noise_only: bool = False) -> np.ndarray:
        """Float (frames, mics) in; the enhanced mono samples that are complete, aligned with the input.

        ``noise_only``: the talker is silent in these samples; MVDR learns the noise from them."""
        core = self.core
        self.pending = np.concatenate([self.pending, samples])
        self.fed += len(samples)
        out = []
        while len(self.pending) >= core.hop:
            new, self.pending = self.pending[:core.hop], self.pending[core.hop:]
            frame = np.concatenate([self.history, new])
            self.history = frame[core.hop:]
            spectra = np.fft.rfft(frame * core.window[:, None], axis=0)  # (bins, mics)
            if noise_only:
                outer = spectra[:, :, None] * np.conj(spectra[:, None, :])
                if self.noise_frames == 0:
                    self.noise = outer + 1e-12 * np.eye(len(spectra[0]))
                else:
                    self.noise = core.smoothing * self.noise + (1 - core.smoothing) * outer
                self.noise_frames += 1
                if self.weights is not None and core.method == "mvdr" and self.noise_frames % 4 == 1:
                    self.weights = self._weights()  # follows the noise, a little at a time
            output = self._apply(self.weights, spectra)
            if self.fade < core.crossfade:
                self.fade += 1
                share = self.fade / core.crossfade
                output = share * output + (1 - share) * self._apply(self.previous, spectra)
            self.ola += np.fft.irfft(output, core.nfft) * core.window
            out.append(self.ola[:core.hop].copy())
            self.ola = np.concatenate([self.ola[core.hop:], np.zeros(core.hop)])
            self.frames += 1
        result = np.concatenate(out) if out else np.zeros(0)
        if self.skip:
            dropped = min(self.skip, len(result))
            result, self.skip = result[dropped:], self.skip - dropped
        self.given += len(result)
        return result

    def flush(self) -> np.ndarray:
        """The output still held back: as many samples as were put in and not yet given out."""
        core = self.core
        owed = self.fed - self.given
        padding = core.nfft - core.hop + (-len(self.pending)) % core.hop
        fed = self.fed
        out = self.process(np.zeros((padding, core.array.mics)))
        self.fed = fed
        return out[:owed]

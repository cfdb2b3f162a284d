"""Direction of arrival for one frame of multi-channel audio, on pyroomacoustics' DOA algorithms.

:class:`Localiser` takes a (frames, mics) float frame, computes its STFT (Hann window, hop
nfft/2) and asks the configured algorithm for ``max_sources`` directions within the frequency
range. Each direction gets a confidence in [0, 1] from the algorithm's spatial spectrum:
``1 - mean / peak`` of the spectrum shifted to a minimum of 0 (0 = flat, no preferred direction;
near 1 = one sharp peak).
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np

from esiaf.arrays import ArrayGeometry

log = logging.getLogger(__name__)

ALGORITHMS = ("NormMUSIC", "MUSIC", "SRP", "TOPS", "CSSM", "WAVES", "FRIDA")
GRID_3D = ("NormMUSIC", "MUSIC", "SRP")  # pyroomacoustics searches the sphere only with these
FRIDA_MAX_CONDITION = 1e8
SPEED_OF_SOUND_M_S = 343.0


class LocaliserError(ValueError):
    """A configuration the localiser cannot work with; the message says why."""


@dataclass(frozen=True)
class Direction:
    azimuth_deg: float  # [0, 360), counter-clockwise from the array's x axis
    elevation_deg: float  # 0 where the array cannot tell
    confidence: float
    relative: float = 1.0  # the spatial spectrum at this direction relative to the strongest one


def _import_pyroomacoustics():
    try:
        import pyroomacoustics
    except ImportError:
        raise LocaliserError("sound source localisation needs pyroomacoustics: "
                             "pip install -e '.[ssl]' (setup.sh installs it)") from None
    return pyroomacoustics


class Localiser:
    def __init__(self, array: ArrayGeometry, sample_rate_hz: int, *, algorithm: str = "NormMUSIC",
                 nfft: int = 256, freq_range_hz: tuple[float, float] = (300.0, 3500.0), max_sources: int = 1):
        pra = _import_pyroomacoustics()
        if algorithm not in ALGORITHMS:
            known = {a.lower(): a for a in ALGORITHMS}
            if algorithm.lower() not in known:
                raise LocaliserError(f"unknown DOA algorithm {algorithm!r}; known: {', '.join(ALGORITHMS)}")
            algorithm = known[algorithm.lower()]
        if nfft < 16 or nfft & (nfft - 1):
            raise LocaliserError(f"nfft must be a power of two of at least 16, not {nfft}")
        low, high = freq_range_hz
        if not 0 <= low < high <= sample_rate_hz / 2:
            raise LocaliserError(f"frequency range {low:g}-{high:g} Hz must be increasing and within "
                                 f"0-{sample_rate_hz / 2:g} Hz (half the sample rate)")
        if (high - low) < 2 * sample_rate_hz / nfft:
            raise LocaliserError(f"frequency range {low:g}-{high:g} Hz holds fewer than two STFT bins "
                                 f"of {sample_rate_hz / nfft:g} Hz (widen it or raise nfft)")
        if not 1 <= max_sources < array.mics:
            raise LocaliserError(f"max_sources must be from 1 to {array.mics - 1} (fewer than the "
                                 f"{array.mics} microphones), not {max_sources}")
        self.array, self.algorithm, self.nfft = array, algorithm, nfft
        self.sample_rate_hz, self.freq_range_hz, self.max_sources = sample_rate_hz, (low, high), max_sources
        self.dim = 3 if array.can_tell_elevation and algorithm in GRID_3D else 2
        if array.can_tell_elevation and self.dim == 2:
            log.warning("%s searches the horizontal plane only: elevation is not reported", algorithm)
        positions = array.positions_m[:self.dim]
        if algorithm == "FRIDA":
            self._check_frida(positions)
        self.window = np.hanning(nfft)
        self._peaks_from_grid = algorithm in GRID_3D
        self._frida_bins: np.ndarray | None = None
        self._doa = pra.doa.algorithms[algorithm](positions, sample_rate_hz, nfft, c=SPEED_OF_SOUND_M_S,
                                                  num_src=max_sources, dim=self.dim)

    @property
    def reports_elevation(self) -> bool:
        return self.dim == 3

    def _check_frida(self, positions: np.ndarray) -> None:
        """FRIDA inverts G^T G per frequency band; refuse arrays where that matrix is singular."""
        from pyroomacoustics.doa.tools_fri_doa_plane import make_G
        if self.array.collinear:
            raise LocaliserError(f"FRIDA cannot localise with {self.array.describe()}: its microphones are "
                                 f"collinear, which makes FRIDA's linear mapping singular; choose another "
                                 f"algorithm (e.g. NormMUSIC)")
        bins = self.freq_bins()
        freqs_hz = bins * self.sample_rate_hz / self.nfft
        max_four = max(self.max_sources + 1, 2)  # FRIDA's own choice (M = K + 1, at least 2)
        matrices = make_G(positions[0], positions[1], 2 * np.pi * freqs_hz, SPEED_OF_SOUND_M_S, max_four,
                          signal_type="visibility")
        worst = max(np.linalg.cond(g.T @ g) for g in matrices)
        if not np.isfinite(worst) or worst > FRIDA_MAX_CONDITION:
            raise LocaliserError(f"FRIDA cannot localise with {self.array.describe()} in "
                                 f"{self.freq_range_hz[0]:g}-{self.freq_range_hz[1]:g} Hz: its linear mapping "
                                 f"is singular (condition number {worst:.1e}); choose another algorithm "
                                 f"(e.g. NormMUSIC)")

    def freq_bins(self) -> np.ndarray:
        low, high = self.freq_range_hz
        step = self.sample_rate_hz / self.nfft
        return np.arange(int(np.ceil(low / step)), int(np.floor(high / step)) + 1)

    def stft(self, frame: np.ndarray) -> np.ndarray:
        """(frames, mics) -> (mics, nfft/2 + 1, snapshots)."""
        hop = self.nfft // 2
        count = 1 + (len(frame) - self.nfft) // hop
        index = np.arange(self.nfft)[None, :] + hop * np.arange(count)[:, None]
        segments = frame.T[:, index] * self.window  # (mics, snapshots, nfft)
        return np.fft.rfft(segments, axis=2).transpose(0, 2, 1)

    def min_frames(self) -> int:
        return 2 * self.nfft  # three snapshots at hop nfft/2

    def locate(self, frame: np.ndarray, floor: NoiseFloor | None = None) -> list[Direction]:
        """Directions of up to ``max_sources`` sources in a (frames, mics) float frame, best first.

        With a ``floor``, only the frequency bins that stand above the background it tracks are
        used; no such bins: no direction.
        """
        if frame.ndim != 2 or frame.shape[1] != self.array.mics:
            raise LocaliserError(f"frame of shape {frame.shape} does not fit {self.array.mics} microphones")
        if len(frame) < self.min_frames():
            raise LocaliserError(f"a frame needs at least {self.min_frames()} samples, not {len(frame)}")
        spectra = self.stft(frame)
        bins = self.freq_bins()
        if floor is not None:
            power = np.mean(np.abs(spectra) ** 2, axis=(0, 2))
            bins = bins[floor.update(power)[bins]]
            if len(bins) < floor.min_bins:
                return []
        if self.algorithm == "FRIDA" and (self._frida_bins is None or not np.array_equal(bins, self._frida_bins)):
            self._doa.G = None  # FRIDA keeps its mapping for the bins it saw first: rebuild it for these
            self._frida_bins = bins
        with warnings.catch_warnings():  # pyroomacoustics warns on ill-conditioned bins; the result says enough
            warnings.simplefilter("ignore")
            # subspace methods lose resolution with a larger signal subspace (4 mics, 3 sources: one noise
            # dimension), so grid searches look for one source and take further peaks of its spectrum
            self._doa.locate_sources(spectra, num_src=1 if self._peaks_from_grid else self.max_sources,
                                     freq_bins=bins)
        azimuths = np.degrees(np.atleast_1d(self._doa.azimuth_recon)) % 360.0
        if self.dim == 3:
            elevations = 90.0 - np.degrees(np.atleast_1d(self._doa.colatitude_recon))
        else:
            elevations = np.zeros_like(azimuths)
        if self._peaks_from_grid and self.max_sources > 1:
            grid = self._doa.grid
            peaks = grid.find_peaks(k=self.max_sources)[::-1]  # strongest first
            azimuths = np.degrees(np.atleast_1d(grid.azimuth[peaks])) % 360.0
            elevations = (90.0 - np.degrees(np.atleast_1d(grid.colatitude[peaks])) if self.dim == 3
                          else np.zeros_like(azimuths))
        confidences = self._confidences(len(azimuths))
        relative = self._relative(azimuths)
        found = [Direction(float(a), float(e), float(c * r), float(r))
                 for a, e, c, r in zip(azimuths, elevations, confidences, relative, strict=False)]
        return sorted(found, key=lambda d: -d.relative)

    def _relative(self, azimuths: np.ndarray) -> np.ndarray:
        """Each direction's spatial-spectrum value relative to the strongest (1 without a grid)."""
        grid = getattr(self._doa, "grid", None)
        values = getattr(grid, "values", None) if grid is not None else None
        grid_azimuths = getattr(grid, "azimuth", None) if grid is not None else None
        if values is None or grid_azimuths is None or len(azimuths) < 2 or not np.all(np.isfinite(values)):
            return np.ones(len(azimuths))
        values = np.asarray(values, dtype=float) - np.min(values)
        nearest = np.argmin(np.abs(np.angle(np.exp(1j * (np.asarray(grid_azimuths)[None, :]
                                                         - np.radians(azimuths)[:, None])))), axis=1)
        strength = values[nearest]
        return strength / strength.max() if strength.max() > 0 else np.ones(len(azimuths))

    def _confidences(self, count: int) -> np.ndarray:
        grid = getattr(self._doa, "grid", None)
        values = getattr(grid, "values", None) if grid is not None else None
        if values is not None and np.size(values) and np.all(np.isfinite(values)):
            shifted = np.asarray(values, dtype=float) - np.min(values)
            peak = float(np.max(shifted))
            return np.full(count, 1.0 - float(np.mean(shifted)) / peak if peak > 0 else 0.0)
        alpha = np.abs(np.atleast_1d(getattr(self._doa, "alpha_recon", np.ones(count)))).reshape(count, -1)
        strength = alpha.mean(axis=1)
        return strength / strength.sum() if strength.sum() > 0 else np.zeros(count)


class NoiseFloor:
    """The background's power per frequency bin, tracked from below (minimum statistics, simplified).

    Per frame the floor falls at once to a quieter bin's power and rises towards a louder one by at
    most ``rise_db_per_s``, so a speaker (seconds long) barely lifts it while a steady noise source
    becomes background within seconds. :meth:`update` tells which bins stand ``snr_db`` above it.
    """

    def __init__(self, frame_s: float, snr_db: float = 6.0, rise_db_per_s: float = 3.0, min_bins: int = 3):
        self.snr = 10 ** (snr_db / 10)
        self.rise = 10 ** (rise_db_per_s * frame_s / 10)
        self.min_bins = min_bins
        self.floor: np.ndarray | None = None

    def update(self, power: np.ndarray) -> np.ndarray:
        if self.floor is None:
            self.floor = power.copy()
            return np.zeros(len(power), dtype=bool)
        above = power > self.snr * self.floor
        self.floor = np.minimum(power, self.floor * self.rise)
        return above

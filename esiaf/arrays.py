"""Microphone array geometries: presets, circular arrays, or positions from a YAML file.

Positions are in metres in the array's own frame: x forward, y left, z up. Azimuths are
counter-clockwise from the x axis (0° = in front, 90° = to the left), elevations up from the
x-y plane. An array whose microphones all lie in one horizontal plane cannot tell a source above
the plane from its mirror image below, so it reports azimuth only (``can_tell_elevation``).

An array is named by a spec string:

- ``pepper4``: Pepper's four head microphones (the 2019 ESIAF's geometry);
- ``respeaker4``: the ReSpeaker USB 4-mic array (mics at (±32 mm, 0) and (0, ±32 mm));
- ``circular:N:RADIUS_M``: N microphones evenly on a circle, the first on the x axis
  (e.g. ``circular:6:0.0463``);
- a path to a YAML file: ``positions: [[x, y, z], ...]`` (z may be left out), optional ``name``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from esiaf.settings import SettingsError, read_yaml_file

PLANAR_TOLERANCE_M = 1e-3


class ArrayError(ValueError):
    """An array spec that names no array, or positions that make none."""


@dataclass(frozen=True)
class ArrayGeometry:
    name: str
    positions_m: np.ndarray  # (3, mics)

    def __post_init__(self) -> None:
        positions = np.asarray(self.positions_m, dtype=float)
        if positions.ndim != 2 or positions.shape[0] != 3:
            raise ArrayError(f"array {self.name}: positions must be (x, y, z) per microphone")
        if positions.shape[1] < 2:
            raise ArrayError(f"array {self.name}: localising needs at least 2 microphones, "
                             f"not {positions.shape[1]}")
        if not np.all(np.isfinite(positions)):
            raise ArrayError(f"array {self.name}: positions must be finite numbers")
        spread = np.linalg.norm(positions[:, :, None] - positions[:, None, :], axis=0)
        if np.any(spread[~np.eye(positions.shape[1], dtype=bool)] < 1e-4):
            raise ArrayError(f"array {self.name}: two microphones share a position")
        object.__setattr__(self, "positions_m", positions)

    @property
    def mics(self) -> int:
        return self.positions_m.shape[1]

    @property
    def can_tell_elevation(self) -> bool:
        """Microphones off one horizontal plane: elevation is observable."""
        return float(np.ptp(self.positions_m[2])) > PLANAR_TOLERANCE_M

    @property
    def collinear(self) -> bool:
        centred = self.positions_m - self.positions_m.mean(axis=1, keepdims=True)
        return np.linalg.matrix_rank(centred, tol=PLANAR_TOLERANCE_M) < 2

    @property
    def aperture_m(self) -> float:
        diff = self.positions_m[:, :, None] - self.positions_m[:, None, :]
        return float(np.max(np.linalg.norm(diff, axis=0)))

    def check_channels(self, channels: int) -> None:
        if channels != self.mics:
            raise ArrayError(f"array {self.name} has {self.mics} microphones but the audio has {channels} "
                             f"channel(s); the channel count must equal the number of microphones "
                             f"(or name the microphones' channels)")

    def select_channels(self, channels: int, mic_channels: list[int]) -> list[int]:
        """The audio's channels that are the microphones, in array order (all of them by default).

        ``channels`` is the audio's channel count (0: not known yet); ``mic_channels`` names the
        microphones' channels where the audio has others too (e.g. the ReSpeaker's 6-channel firmware:
        processed audio on 0, the microphones on 1-4, playback on 5).
        """
        if not mic_channels:
            if channels:
                self.check_channels(channels)
            return list(range(self.mics))
        if len(mic_channels) != self.mics or len(set(mic_channels)) != len(mic_channels):
            raise ArrayError(f"array {self.name} has {self.mics} microphones: name {self.mics} distinct channels "
                             f"for them, not {list(mic_channels)}")
        wrong = [c for c in mic_channels if c < 0 or (channels and c >= channels)]
        if wrong:
            have = f"audio of {channels} channel(s) (0 to {channels - 1})" if channels else "the audio"
            raise ArrayError(f"microphone channels {wrong} do not exist in {have}")
        return list(mic_channels)

    def describe(self) -> str:
        return (f"{self.name} ({self.mics} mics, aperture {self.aperture_m * 100:.1f} cm, "
                f"{'3-D' if self.can_tell_elevation else 'planar'})")


def _planar(name: str, xy: list[tuple[float, float]]) -> ArrayGeometry:
    points = np.array(xy, dtype=float).T
    return ArrayGeometry(name, np.vstack([points, np.zeros(points.shape[1])]))


def circular(mics: int, radius_m: float, name: str = "") -> ArrayGeometry:
    if mics < 2:
        raise ArrayError(f"a circular array needs at least 2 microphones, not {mics}")
    if not radius_m > 0:
        raise ArrayError(f"a circular array needs a positive radius in metres, not {radius_m}")
    angles = 2 * np.pi * np.arange(mics) / mics
    return _planar(name or f"circular:{mics}:{radius_m:g}",
                   list(zip(radius_m * np.cos(angles), radius_m * np.sin(angles), strict=True)))


PRESETS = {
    # x, y in metres as in the original ESIAF's SSL component (Pepper's head, front is +x)
    "pepper4": lambda: _planar("pepper4", [(-0.0267, 0.0343), (-0.0267, -0.0343),
                                           (0.0313, 0.0343), (0.0313, -0.0343)]),
    # channel order as the device delivers its 4 processed-free mic channels (ODAS' mics_respeaker_usb)
    "respeaker4": lambda: _planar("respeaker4", [(-0.032, 0.0), (0.0, -0.032), (0.032, 0.0), (0.0, 0.032)]),
}


def from_positions(positions: list, name: str) -> ArrayGeometry:
    try:
        rows = [list(map(float, p)) for p in positions]
    except (TypeError, ValueError):
        raise ArrayError(f"array {name}: positions must be a list of [x, y] or [x, y, z] in metres") from None
    if not rows or any(len(r) not in (2, 3) for r in rows):
        raise ArrayError(f"array {name}: positions must be a list of [x, y] or [x, y, z] in metres")
    return ArrayGeometry(name, np.array([r + [0.0] * (3 - len(r)) for r in rows]).T)


def load_array(spec: str) -> ArrayGeometry:
    """An array from its spec string (see the module's doc); raises ArrayError with one clear line."""
    spec = spec.strip()
    if spec in PRESETS:
        return PRESETS[spec]()
    if spec.startswith("circular:"):
        parts = spec.split(":")
        try:
            mics, radius_m = int(parts[1]), float(parts[2])
        except (IndexError, ValueError):
            raise ArrayError(f"circular array spec must be circular:MICS:RADIUS_M, not {spec!r}") from None
        if len(parts) != 3:
            raise ArrayError(f"circular array spec must be circular:MICS:RADIUS_M, not {spec!r}")
        return circular(mics, radius_m)
    path = Path(spec)
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            data = read_yaml_file(path)
        except SettingsError as exc:
            raise ArrayError(str(exc)) from None
        if "positions" not in data:
            raise ArrayError(f"array file {path} must hold a mapping with 'positions: [[x, y, z], ...]'")
        unknown = set(data) - {"name", "positions"}
        if unknown:
            raise ArrayError(f"array file {path}: unknown keys {', '.join(sorted(unknown))}; "
                             f"known: name, positions")
        return from_positions(data["positions"], str(data.get("name") or path.stem))
    raise ArrayError(f"unknown array {spec!r}; give one of {', '.join(PRESETS)}, circular:MICS:RADIUS_M "
                     f"or a YAML file of positions")


ARRAY_CHOICES = "pepper4, respeaker4, circular:MICS:RADIUS_M or a YAML file of positions"  # what `array` takes


def array_input(spec: str, channels: int, mic_channels: list[int]) -> tuple[ArrayGeometry, list[int], int]:
    """An array consumer's input from its settings: the geometry, the microphones' channels in array
    order, and the input's channel count (``channels``, or as many as the microphones need)."""
    array = load_array(spec)
    selected = array.select_channels(channels, mic_channels)
    return array, selected, channels or (max(selected) + 1 if mic_channels else array.mics)


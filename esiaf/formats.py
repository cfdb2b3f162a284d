"""Audio formats and the codec between wire bytes and numpy arrays.

A format is a sample rate, a sample type, an endianness and a channel count;
samples are interleaved. ``decode`` turns a payload into an array of shape
(frames, channels) in the sample type's natural numpy dtype (int24 as int32);
``encode`` does the reverse. Conversion between formats is in esiaf/convert.py.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from esiaf.proto import esiaf_pb2 as pb

# name -> (bytes per sample, numpy kind for decode, signed)
_TYPES: dict[str, tuple[int, str, bool]] = {
    "int8": (1, "i1", True), "uint8": (1, "u1", False),
    "int16": (2, "i2", True), "uint16": (2, "u2", False),
    "int24": (3, "i4", True), "uint24": (3, "u4", False),
    "int32": (4, "i4", True), "uint32": (4, "u4", False),
    "float32": (4, "f4", True), "float64": (8, "f8", True),
}
SAMPLE_TYPES = tuple(_TYPES)
_PB_TYPE = {name: getattr(pb, f"SAMPLE_TYPE_{name.upper()}") for name in _TYPES}
_PB_TYPE_NAME = {v: k for k, v in _PB_TYPE.items()}
_PB_ENDIAN = {"little": pb.ENDIANNESS_LITTLE, "big": pb.ENDIANNESS_BIG}
# formats read from messages, by their fields: every received message names its format, and a format
# made anew (and validated) per message is a measurable share of a consumer's CPU per chunk;
# bounded, as peers choose what they send
_FROM_PROTO: dict[tuple[int, int, int, int], AudioFormat] = {}
MAX_FORMATS_KEPT = 64


class FormatError(ValueError):
    """A format that cannot be used, or a payload that does not fit its format."""


@dataclass(frozen=True)
class AudioFormat:
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    endianness: str = "little"
    channels: int = 1

    def __post_init__(self) -> None:
        if self.sample_type not in _TYPES:
            raise FormatError(f"unknown sample type {self.sample_type!r}; known: {', '.join(_TYPES)}")
        if self.endianness not in _PB_ENDIAN:
            raise FormatError(f"endianness must be 'little' or 'big', not {self.endianness!r}")
        if self.sample_rate_hz <= 0:
            raise FormatError(f"sample rate must be positive, not {self.sample_rate_hz}")
        if self.channels <= 0:
            raise FormatError(f"channel count must be positive, not {self.channels}")

    @property
    def bytes_per_sample(self) -> int:
        return _TYPES[self.sample_type][0]

    @property
    def bytes_per_frame(self) -> int:
        return self.bytes_per_sample * self.channels

    @property
    def bits_per_second(self) -> int:
        return self.channels * self.bytes_per_sample * 8 * self.sample_rate_hz

    @property
    def full_scale(self) -> float:
        """Magnitude of a full-scale sample (1.0 for floats)."""
        size, kind, _signed = _TYPES[self.sample_type]
        if kind[0] == "f":
            return 1.0
        return float(2 ** (8 * size - 1))

    def frames_in(self, payload: bytes) -> int:
        if len(payload) % self.bytes_per_frame:
            raise FormatError(
                f"payload of {len(payload)} bytes is not a whole number of {self.bytes_per_frame}-byte frames ({self})")
        return len(payload) // self.bytes_per_frame

    def duration_ns(self, frames: int) -> int:
        return frames * 1_000_000_000 // self.sample_rate_hz

    def __str__(self) -> str:
        return f"{self.sample_rate_hz} Hz {self.sample_type} {self.endianness}-endian {self.channels} ch"

    # conversions to the other representations
    def to_proto(self) -> pb.AudioFormat:
        return pb.AudioFormat(sample_rate_hz=self.sample_rate_hz, sample_type=_PB_TYPE[self.sample_type],
                              endianness=_PB_ENDIAN[self.endianness], channels=self.channels)

    @classmethod
    def from_proto(cls, msg: pb.AudioFormat) -> AudioFormat:
        key = (msg.sample_rate_hz, msg.sample_type, msg.endianness, msg.channels)
        if cls is AudioFormat and (known := _FROM_PROTO.get(key)) is not None:
            return known  # frozen: one instance serves every message in that format
        if msg.sample_type not in _PB_TYPE_NAME:
            raise FormatError(f"unknown sample type {msg.sample_type} in message")
        fmt = cls(sample_rate_hz=msg.sample_rate_hz, sample_type=_PB_TYPE_NAME[msg.sample_type],
                  endianness="big" if msg.endianness == pb.ENDIANNESS_BIG else "little",
                  channels=msg.channels)
        if cls is AudioFormat and len(_FROM_PROTO) < MAX_FORMATS_KEPT:
            _FROM_PROTO[key] = fmt
        return fmt

    def to_dict(self) -> dict[str, Any]:
        return {"sample_rate_hz": self.sample_rate_hz, "sample_type": self.sample_type,
                "endianness": self.endianness, "channels": self.channels}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AudioFormat:
        return cls(**data)


@lru_cache(maxsize=MAX_FORMATS_KEPT)
def _dtype(fmt: AudioFormat) -> np.dtype:
    size, kind, _ = _TYPES[fmt.sample_type]
    order = ">" if fmt.endianness == "big" else "<"
    return np.dtype(order + (kind[0] + "1" if size == 3 else kind))


@lru_cache(maxsize=MAX_FORMATS_KEPT)
def _native_dtype(fmt: AudioFormat) -> np.dtype:
    return _dtype(fmt).newbyteorder("=")


def decode(payload: bytes, fmt: AudioFormat) -> np.ndarray:
    """Payload bytes -> array (frames, channels), native byte order."""
    frames = fmt.frames_in(payload)
    if fmt.bytes_per_sample != 3:
        data = np.frombuffer(payload, dtype=_dtype(fmt)).astype(_native_dtype(fmt), copy=False)
        return data.reshape(frames, fmt.channels)
    raw = np.frombuffer(payload, dtype=np.uint8).reshape(-1, 3).astype(np.uint32)
    if fmt.endianness == "big":
        raw = raw[:, ::-1]
    value = raw[:, 0] | (raw[:, 1] << 8) | (raw[:, 2] << 16)
    if fmt.sample_type == "int24":
        value = value.astype(np.int32)
        value = np.where(value >= 1 << 23, value - (1 << 24), value).astype(np.int32)
    return value.reshape(frames, fmt.channels)


def encode(samples: np.ndarray, fmt: AudioFormat) -> bytes:
    """Array (frames, channels) or (frames,) for mono -> payload bytes. No scaling, no clipping."""
    samples = np.asarray(samples)
    if samples.ndim == 1:
        samples = samples.reshape(-1, 1)
    if samples.ndim != 2 or samples.shape[1] != fmt.channels:
        raise FormatError(f"samples of shape {samples.shape} do not fit {fmt.channels} channel(s)")
    if fmt.bytes_per_sample != 3:
        return np.ascontiguousarray(samples, dtype=_dtype(fmt)).tobytes()
    value = samples.astype(np.int64).reshape(-1) & 0xFFFFFF
    raw = np.stack([(value >> shift) & 0xFF for shift in (0, 8, 16)], axis=1).astype(np.uint8)
    if fmt.endianness == "big":
        raw = raw[:, ::-1]
    return np.ascontiguousarray(raw).tobytes()


def to_float(samples: np.ndarray, fmt: AudioFormat) -> np.ndarray:
    """Samples in ``fmt``'s type -> float64 in [-1, 1)."""
    size, kind, signed = _TYPES[fmt.sample_type]
    out = samples.astype(np.float64)
    if kind[0] == "f":
        return out
    if not signed:
        out -= 2 ** (8 * size - 1)
    return out / fmt.full_scale


def peak(samples: np.ndarray, fmt: AudioFormat) -> float:
    """Largest magnitude of the chunk relative to full scale (0..1)."""
    if samples.size == 0:
        return 0.0
    _size, kind, signed = _TYPES[fmt.sample_type]
    if kind[0] != "f" and signed:
        return float(np.max(np.abs(samples.astype(np.int64)))) / fmt.full_scale
    return float(np.max(np.abs(to_float(samples, fmt))))

"""A Wyoming client's audio, whatever its rate, sample width and channel count, as the mono 16-bit
audio the service publishes: channels averaged, soxr's streaming resampler kept across chunks."""
from __future__ import annotations

import numpy as np
import soxr

from esiaf.convert import RESAMPLE_QUALITY, from_float
from esiaf.formats import AudioFormat, FormatError, decode, to_float

SAMPLE_TYPES = {1: "uint8", 2: "int16", 3: "int24", 4: "int32"}  # Wyoming's width in bytes, as WAV has them
MIN_RATE_HZ, MAX_RATE_HZ = 8_000, 192_000  # what the components take (esiaf/receiving.py)
MAX_CHANNELS = 8


class AudioError(ValueError):
    """The client's audio cannot be read as it says it is."""


def client_format(rate: object, width: object, channels: object) -> AudioFormat:
    """The format an audio-start or audio-chunk declares, checked."""
    if not isinstance(rate, int) or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise AudioError(f"rate {rate!r}: give {MIN_RATE_HZ} to {MAX_RATE_HZ} Hz")
    if width not in SAMPLE_TYPES:
        raise AudioError(f"width {width!r}: give 1, 2, 3 or 4 bytes per sample")
    if not isinstance(channels, int) or not 1 <= channels <= MAX_CHANNELS:
        raise AudioError(f"channels {channels!r}: give 1 to {MAX_CHANNELS}")
    return AudioFormat(rate, SAMPLE_TYPES[width], "little", channels)


class ClientAudio:
    """One session's conversion to ``target`` (mono): what it holds between chunks is soxr's state."""

    def __init__(self, source: AudioFormat, target: AudioFormat):
        self.source, self.target = source, target
        self._resampler = soxr.ResampleStream(source.sample_rate_hz, target.sample_rate_hz, 1, dtype="float32",
                                              quality=RESAMPLE_QUALITY) \
            if source.sample_rate_hz != target.sample_rate_hz else None

    def convert(self, payload: bytes, last: bool = False) -> np.ndarray:
        """A chunk in the source format -> samples in the target's (``last``: with what soxr held back)."""
        if len(payload) % self.source.bytes_per_frame:
            raise AudioError(f"an audio chunk of {len(payload)} bytes is not a whole number of "
                             f"{self.source.bytes_per_frame}-byte frames ({self.source})")
        try:
            samples = decode(payload, self.source)
        except FormatError as exc:
            raise AudioError(str(exc)) from None
        mono = to_float(samples, self.source).astype("float32").mean(axis=1)
        if self._resampler is not None:
            mono = self._resampler.resample_chunk(mono, last=last)
        return from_float(mono, self.target).astype(self.target.sample_type).reshape(-1, 1)

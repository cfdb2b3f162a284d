"""Audio as handlers see it, and the sample clock that stamps capture time."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from esiaf.formats import AudioFormat, decode, peak, to_float
from esiaf.proto import esiaf_pb2 as pb


@dataclass
class Audio:
    """One received chunk: capture time span, format, payload and meta information."""

    topic: str
    stream_id: str
    publisher: str
    sequence: int
    start_ns: int
    end_ns: int
    format: AudioFormat
    payload: bytes
    meta: pb.AudioMeta = field(default_factory=pb.AudioMeta)

    @classmethod
    def from_message(cls, msg: pb.AugmentedAudio) -> Audio:
        return cls(topic=msg.topic, stream_id=msg.stream_id, publisher=msg.publisher, sequence=msg.sequence,
                   start_ns=msg.start_ns, end_ns=msg.end_ns, format=AudioFormat.from_proto(msg.format),
                   payload=msg.payload, meta=msg.meta)

    @cached_property
    def samples(self) -> np.ndarray:
        """(frames, channels) in the format's sample type."""
        return decode(self.payload, self.format)

    @property
    def frames(self) -> int:
        return self.format.frames_in(self.payload)

    def as_float(self) -> np.ndarray:
        """(frames, channels) as float64 in [-1, 1)."""
        return to_float(self.samples, self.format)

    def peak(self) -> float:
        return peak(self.samples, self.format)

    @property
    def segmentation_ended(self) -> bool:
        return self.meta.segmentation_ended

    @property
    def end_of_stream(self) -> bool:
        return self.meta.end_of_stream

    @property
    def ssl_directions(self) -> list[pb.SslDirection]:
        return list(self.meta.ssl_directions)


class SampleClock:
    """Capture time from sample counts: ``origin_ns + frames * 1e9 / rate``, exact in integers.

    Never stamps from the wall clock per chunk, so timestamps do not jitter or
    drift with scheduling; only the origin comes from the wall clock.
    """

    def __init__(self, origin_ns: int, sample_rate_hz: int):
        self.origin_ns = origin_ns
        self.sample_rate_hz = sample_rate_hz
        self.frames = 0

    def time_at(self, frames: int) -> int:
        return self.origin_ns + frames * 1_000_000_000 // self.sample_rate_hz

    def advance(self, frames: int) -> tuple[int, int]:
        """Returns the (start_ns, end_ns) of the next ``frames`` frames and moves on."""
        start_ns = self.time_at(self.frames)
        self.frames += frames
        return start_ns, self.time_at(self.frames)

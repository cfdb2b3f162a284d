"""SSL service: where sound comes from, per frame of multi-channel audio, tracked into sources.

The incoming chunks are cut into frames of ``frame_ms`` on the sample stream. Per frame:

- level (RMS over all channels, 96 dB = full scale) below ``min_level_db``, or a confidence below
  ``min_confidence``: a ``nothing`` result (SSL, span = the frame) says "covered, no source here",
  so fusion need not wait for a direction that will never come;
- otherwise an SSL result with up to ``max_sources`` directions (azimuth, elevation where the
  array can tell, confidence; a second or third peak only if at least ``min_relative`` as strong
  as the first), each with the id of the tracked source it belongs to, and marked ``background``
  where that track has stayed in one place for ``background_s`` (a loudspeaker, not a talker). With
  the robot's own loudspeaker direction known, a direction within ``self_width_deg`` / 2 of it is the
  robot itself: its ``source_id`` is ``self`` and it is ``background`` (fusion never takes it for the
  talker, the beamformer never steers at it, and the robot's own voice heard back is told by it). The
  direction is learnt per stream from the player's reference (``reference_topic``, what the robot
  plays: ``self_direction.py``) once enough frames were localised while it played; until then, and
  without a reference, it is the ``self_azimuth_deg`` setting (None: not marked).

Every chunk is forwarded unchanged on ``output_topic`` once its samples have been localised,
carrying the directions of the frame it ends in as SSL meta. The end of a stream's last frame,
shorter than a frame, is localised if long enough and covered with ``nothing`` otherwise.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import Field

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError, ssl_direction
from esiaf.arrays import ARRAY_CHOICES, array_input
from esiaf.per_stream import PerStream
from esiaf.proto import esiaf_pb2 as pb
from esiaf_services.ssl.doa import Localiser, LocaliserError, NoiseFloor
from esiaf_services.ssl.self_direction import SelfDirection
from esiaf_services.ssl.tracker import Tracker

log = logging.getLogger(__name__)
SELF = "self"  # the source id of a direction at the robot's own loudspeaker


class SslSettings(ComponentSettings):
    input_topic: str = "grabber/audio"
    output_topic: str = "ssl/audio"  # the input, forwarded with SSL meta
    array: str = "respeaker4"  # pepper4, respeaker4, circular:MICS:RADIUS_M, or a YAML file of positions
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    channels: int = 0  # of the input; 0 = as many as mic_channels names, or the array's microphones
    # input channels that are the array's microphones, in array order; [] = all
    mic_channels: list[int] = Field(default_factory=list)
    algorithm: str = "NormMUSIC"  # MUSIC, NormMUSIC, SRP, TOPS, CSSM, WAVES, FRIDA
    nfft: int = 256
    freq_min_hz: float = 300.0
    freq_max_hz: float = 5000.0
    frame_ms: float = 128.0
    max_sources: int = 3  # directions per frame (fewer than the microphones)
    min_relative: float = 0.6  # a second or third peak counts if this strong relative to the first
    min_level_db: float = 50.0  # frame RMS level; quieter frames are "nothing here"
    min_confidence: float = 0.0
    bin_snr_db: float = 6.0  # use only frequency bins this far above the tracked background (0 = all bins)
    floor_rise_db_per_s: float = 3.0  # how fast the background estimate may rise
    gate_deg: float = 12.0  # tracking: a direction this close to a live track continues it
    hold_ms: float = 1500.0  # tracking: a source unseen this long has ended
    background_s: float = 8.0  # a track this old is background (0 = never)
    # the robot's own loudspeaker, counter-clockwise from the array's x axis (None: not marked), and how wide
    self_azimuth_deg: float | None = None
    self_width_deg: float = Field(default=40.0, gt=0, le=360)
    # what the robot's loudspeaker plays (player/audio), to learn its direction from; "" = none (the setting)
    reference_topic: str = ""
    self_min_frames: int = Field(default=20, ge=1)  # localised frames while it plays before a direction is learnt


@dataclass
class StreamState:
    tracker: Tracker
    floor: NoiseFloor | None
    self_direction: SelfDirection
    chunks: list[Audio] = field(default_factory=list)  # not yet fully localised
    samples: list[np.ndarray] = field(default_factory=list)
    buffered: int = 0  # frames of samples not yet localised
    offset: int = 0  # how many samples of chunks[0] were localised already
    announced: float | None = None  # the learnt own direction last logged


class Ssl(Component):
    """Sound source localisation on a microphone array (pyroomacoustics DOA), with tracking."""

    service = "ssl"
    kind = "ssl"
    Settings = SslSettings
    settings: SslSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {
        "array": ARRAY_CHOICES,
        "algorithm": "DOA algorithm: NormMUSIC (default), MUSIC, SRP, TOPS, CSSM, WAVES, FRIDA"}

    def __init__(self, settings: SslSettings):
        super().__init__(settings)
        try:
            self.array, self.mic_channels, channels = array_input(settings.array, settings.channels,
                                                                  settings.mic_channels)
            self.format = AudioFormat(settings.sample_rate_hz, settings.sample_type, channels=channels)
        except ValueError as exc:
            raise SetupError(f"bad SSL settings: {exc}") from None
        if settings.frame_ms <= 0:
            raise SetupError(f"frame_ms must be positive, not {settings.frame_ms}")
        self.frame_frames = round(settings.frame_ms * settings.sample_rate_hz / 1000)
        self.add_input(settings.input_topic, self.format)
        self.add_output(settings.output_topic, self.format)
        if settings.reference_topic:
            self.add_input(settings.reference_topic, AudioFormat(settings.sample_rate_hz, settings.sample_type,
                                                                 channels=1))
        self.localiser: Localiser | None = None
        self.streams: PerStream[StreamState] = PerStream(lambda _: self._new_stream(), settings.max_streams, "tracker",
                                                         info=self.info)
        self.counts = {"located": 0, "nothing": 0}

    def setup(self) -> None:
        s = self.settings
        try:
            self.localiser = Localiser(self.array, s.sample_rate_hz, algorithm=s.algorithm, nfft=s.nfft,
                                       freq_range_hz=(s.freq_min_hz, s.freq_max_hz), max_sources=s.max_sources)
            Tracker(s.gate_deg, s.hold_ms, background_s=s.background_s)  # validates the tracking settings
            if not 0 <= s.min_relative <= 1:
                raise ValueError(f"min_relative must be in [0, 1], not {s.min_relative}")
        except (LocaliserError, ValueError) as exc:
            raise SetupError(f"bad SSL settings: {exc}") from None
        if self.frame_frames < self.localiser.min_frames():
            raise SetupError(f"frame_ms {s.frame_ms:g} is shorter than two STFT windows of nfft {s.nfft} "
                             f"({2 * s.nfft * 1000 / s.sample_rate_hz:g} ms)")
        self.info.update(array=self.array.describe(), algorithm=self.localiser.algorithm,
                         elevation=self.localiser.reports_elevation)
        log.info("localising array=%s algorithm=%s nfft=%d frame_ms=%g band=%g-%g Hz", self.array.describe(),
                 self.localiser.algorithm, s.nfft, s.frame_ms, s.freq_min_hz, s.freq_max_hz)

    def stream_inputs(self) -> set[str]:
        return {self.settings.input_topic}  # the player's reference may never end

    def on_audio(self, audio: Audio) -> None:
        if self.settings.reference_topic and audio.topic == self.settings.reference_topic:
            if audio.frames:  # (a reference after its stream's end makes a state that max_streams bounds)
                self.streams.get(audio.stream_id).self_direction.reference(audio.start_ns, audio.end_ns,
                                                                           audio.as_float()[:, 0])
            return
        state = self.streams.get(audio.stream_id)
        if audio.frames:
            state.chunks.append(audio)
            state.samples.append(audio.as_float()[:, self.mic_channels])
            state.buffered += audio.frames
        while state.buffered >= self.frame_frames:
            self._localise(state, self.frame_frames)
        if audio.end_of_stream and state.buffered:
            self._localise(state, state.buffered)

    def _new_stream(self) -> StreamState:
        s = self.settings
        floor = NoiseFloor(s.frame_ms / 1000, s.bin_snr_db, s.floor_rise_db_per_s) if s.bin_snr_db > 0 else None
        return StreamState(Tracker(s.gate_deg, s.hold_ms, background_s=s.background_s), floor,
                           SelfDirection(s.self_width_deg, min_frames=s.self_min_frames))

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        self.streams.pop(stream_id)
        super().on_end_of_stream(stream_id, audio)

    def _localise(self, state: StreamState, count: int) -> None:
        """Localises the next ``count`` buffered samples; forwards the chunks that end in them."""
        samples = np.concatenate(state.samples)
        frame, rest = samples[:count], samples[count:]
        state.samples, state.buffered = ([rest] if len(rest) else []), len(rest)
        first = state.chunks[0]
        start_ns = time_at(first, state.offset)
        # walk the chunks this frame covers: those that end inside it are done
        done, position = [], state.offset
        remaining = count
        while state.chunks and state.chunks[0].frames - position <= remaining:
            remaining -= state.chunks[0].frames - position
            done.append(state.chunks.pop(0))
            position = 0
        state.offset = position + remaining if state.chunks else 0
        end_ns = time_at(state.chunks[0], state.offset) if state.chunks and state.offset else done[-1].end_ns
        directions = self._directions(state, frame, (start_ns, end_ns), first.stream_id)
        for chunk in done:
            self.forward(self.settings.output_topic, chunk, ssl_directions=directions)

    def _directions(self, state: StreamState, frame: np.ndarray, span: tuple[int, int],
                    stream_id: str) -> list[pb.SslDirection]:
        s = self.settings
        assert self.localiser is not None  # setup() makes it
        level_db = 96.0 + 10 * math.log10(float(np.mean(frame ** 2)) + 1e-20)
        reason = ""
        if level_db < s.min_level_db:
            reason = f"level {level_db:.1f} dB below min_level_db {s.min_level_db:g}"
        elif len(frame) < self.localiser.min_frames():
            reason = f"{len(frame)} samples at the stream's end: too short to localise"
        else:
            found = [d for d in self.localiser.locate(frame, state.floor) if d.confidence >= s.min_confidence
                     and d.relative >= s.min_relative]
            if not found:
                reason = f"no direction with confidence >= {s.min_confidence:g}"
                if state.floor is not None:
                    reason = (f"fewer than {state.floor.min_bins} frequency bins {s.bin_snr_db:g} dB above the "
                              f"background, or {reason}")
        if reason:
            self.counts["nothing"] += 1
            self.info["frames"] = dict(self.counts)
            self.emit("ssl", span, stream_id=stream_id, nothing=reason)
            return []
        tracks = state.tracker.update(span[1], [d.azimuth_deg for d in found])
        directions = [ssl_direction(d.azimuth_deg, d.elevation_deg, d.confidence, source_id=t.source_id)
                      for d, t in zip(found, tracks, strict=True)]
        learnt = state.self_direction
        learnt.frame(span[0], span[1], [d.azimuth_deg for d in found])
        self_azimuth = learnt.azimuth_deg if learnt.azimuth_deg is not None else s.self_azimuth_deg
        if learnt.azimuth_deg is not None and (state.announced is None or abs(
                (learnt.azimuth_deg - state.announced + 180.0) % 360.0 - 180.0) >= 5.0):
            state.announced = learnt.azimuth_deg
            self.info["self_azimuth_deg"] = round(learnt.azimuth_deg)  # the last stream's, in the heartbeat
            log.info("stream_id=%s: the robot's own direction learnt: %.0f deg", stream_id, learnt.azimuth_deg)
        for direction, track in zip(directions, tracks, strict=True):
            direction.elevation_known = self.localiser.reports_elevation
            direction.track_azimuth_deg = track.azimuth_deg
            direction.background = track.background
            if self_azimuth is not None and \
                    abs((direction.azimuth_deg - self_azimuth + 180.0) % 360.0 - 180.0) <= s.self_width_deg / 2:
                direction.source_id, direction.background = SELF, True
        self.counts["located"] += 1
        self.info["frames"] = dict(self.counts)
        self.emit("ssl", span, stream_id=stream_id,
                  ssl=pb.SslResult(directions=directions, algorithm=self.localiser.algorithm, level_db=level_db))
        return directions


def time_at(chunk: Audio, offset: int) -> int:
    """Capture time of sample ``offset`` of a chunk."""
    if offset >= chunk.frames:
        return chunk.end_ns
    return chunk.start_ns + (chunk.end_ns - chunk.start_ns) * offset // chunk.frames

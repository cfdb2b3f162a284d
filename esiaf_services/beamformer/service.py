"""Beamformer service: the array's audio, steered at the current talker, out as one enhanced channel.

It reads the multi-channel audio that the ssl service forwards with SSL meta (``ssl/audio``) and
publishes mono audio (``beamformer/audio``) with the same capture times, for the VAD, the
recogniser and the other analysers. Per stream:

- **the talker** is the strongest direction in a chunk's SSL meta whose track is not marked
  background (a loudspeaker, a TV); the current talker's track is kept while it is heard (another
  must be twice as confident to take over) and for ``hold_ms`` after it was last heard, so short
  pauses between words do not unsteer the beam; then it passes the reference microphone again;
- **steering** uses the track's smoothed azimuth; changes are cross-faded (no clicks);
- **the noise** (for MVDR) is learnt on the chunks whose SSL meta holds no talker;
- with no talker tracked the reference microphone passes, unchanged; a stream whose first
  ``no_meta_warn_s`` carried no SSL meta at all is reported once in the log (is the ssl service
  in front of it?).

Methods: ``mvdr`` (default) and ``das`` (delay and sum); see :mod:`esiaf_services.beamformer.beam`.
The output lags the input by nothing in capture time: each chunk is published, with its own
timestamps, once its enhanced samples are complete (``nfft/2`` samples of look-ahead).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import Field

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from esiaf.arrays import ARRAY_CHOICES, ArrayError, array_input
from esiaf.per_stream import PerStream
from esiaf_services.beamformer.beam import BeamCore, BeamformerError, BeamStream

log = logging.getLogger(__name__)
NS = 1_000_000_000


class BeamformerSettings(ComponentSettings):
    input_topic: str = "ssl/audio"
    output_topic: str = "beamformer/audio"
    array: str = "respeaker4"  # pepper4, respeaker4, circular:MICS:RADIUS_M, or a YAML file of positions
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    channels: int = 0  # of the input; 0 = as many as mic_channels names, or the array's microphones
    # input channels that are the array's microphones, in array order; [] = all
    mic_channels: list[int] = Field(default_factory=list)
    method: str = "mvdr"  # mvdr | das
    nfft: int = 512
    reference_mic: int = 0  # passed through where no talker is tracked
    loading: float = 0.001  # MVDR diagonal loading, relative to the noise power
    noise_smoothing: float = 0.98  # MVDR: weight of the old noise covariance per frame (nfft/2 samples)
    crossfade_ms: float = 64.0
    hold_ms: float = 1000.0  # keep steering at a talker unheard this long
    no_meta_warn_s: float = 5.0


@dataclass
class StreamState:
    beam: BeamStream
    chunks: list[Audio] = field(default_factory=list)  # waiting for their enhanced samples
    ready: np.ndarray = field(default_factory=lambda: np.zeros(0))  # enhanced, not yet published
    source_id: str = ""  # the talker's track
    confidence: float = 0.0
    last_heard_ns: int = 0
    first_ns: int | None = None
    meta_seen: bool = False
    warned: bool = False


class Beamformer(Component):
    """Steers the microphone array at the tracked talker (MVDR or delay-and-sum)."""

    service = "beamformer"
    kind = "other"
    Settings = BeamformerSettings
    settings: BeamformerSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {"array": ARRAY_CHOICES,
                                         "method": "mvdr (default) or das (delay and sum)"}

    def __init__(self, settings: BeamformerSettings):
        super().__init__(settings)
        try:
            self.array, self.mic_channels, channels = array_input(settings.array, settings.channels,
                                                                  settings.mic_channels)
            self.format = AudioFormat(settings.sample_rate_hz, settings.sample_type, channels=channels)
            frame_s = settings.nfft / 2 / settings.sample_rate_hz
            self.core = BeamCore(self.array, settings.sample_rate_hz, method=settings.method, nfft=settings.nfft,
                                 reference_mic=settings.reference_mic, loading=settings.loading,
                                 noise_smoothing=settings.noise_smoothing,
                                 crossfade_frames=max(1, round(settings.crossfade_ms / 1000 / frame_s)))
        except (ArrayError, BeamformerError, ValueError) as exc:
            raise SetupError(f"bad beamformer settings: {exc}") from None
        self.add_input(settings.input_topic, self.format)
        self.add_output(settings.output_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.streams: PerStream[StreamState] = PerStream(lambda _: StreamState(self.core.stream()),
                                                         settings.max_streams, "beamformer", info=self.info)
        self._ended_on_chunk: set[str] = set()  # streams whose end went out with their last chunk
        self.info.update(array=self.array.describe(), method=settings.method)

    def setup(self) -> None:
        log.info("beamforming array=%s method=%s nfft=%d", self.array.describe(), self.settings.method,
                 self.settings.nfft)

    def on_audio(self, audio: Audio) -> None:
        state = self.streams.get(audio.stream_id)
        talker = self._talker(state, audio)
        state.beam.steer(talker)
        if audio.frames:
            state.chunks.append(audio)
            noise_only = state.meta_seen and not self._talkers(audio)
            enhanced = state.beam.process(audio.as_float()[:, self.mic_channels], noise_only=noise_only)
            state.ready = np.concatenate([state.ready, enhanced])
        if audio.end_of_stream:
            state.ready = np.concatenate([state.ready, state.beam.flush()])
        self._publish_ready(audio.stream_id, state, audio.end_of_stream)

    def _talkers(self, audio: Audio):
        """The meta's directions that may be a talker: not background, and numbers a peer could not
        have broken (a non-finite azimuth would make every weight NaN)."""
        return [d for d in audio.ssl_directions if not d.background and math.isfinite(d.azimuth_deg)
                and math.isfinite(d.track_azimuth_deg) and math.isfinite(d.probability)]

    def _talker(self, state: StreamState, audio: Audio) -> float | None:
        """The azimuth to steer at for this chunk, or None for the reference microphone."""
        if state.first_ns is None:
            state.first_ns = audio.start_ns
        if audio.ssl_directions:
            state.meta_seen = True
        elif not state.meta_seen and not state.warned and audio.end_ns - state.first_ns >= \
                self.settings.no_meta_warn_s * NS:
            state.warned = True
            log.warning("stream_id=%s: no SSL meta in its first %g s: passing microphone %d (is the ssl "
                        "service in front, input_topic=%s?)", audio.stream_id, self.settings.no_meta_warn_s,
                        self.settings.reference_mic, self.settings.input_topic)
        talkers = self._talkers(audio)
        if talkers:
            best = max(talkers, key=lambda d: d.probability)
            current = next((d for d in talkers if d.source_id == state.source_id), None)
            chosen = current if current is not None and best.probability < 2 * max(current.probability, 1e-9) \
                else best
            state.source_id, state.last_heard_ns = chosen.source_id, audio.end_ns
            # the track's smoothed azimuth where the ssl service gave one (0 = unset), else this frame's
            return chosen.track_azimuth_deg if chosen.source_id and chosen.track_azimuth_deg else chosen.azimuth_deg
        if state.source_id and audio.end_ns - state.last_heard_ns <= self.settings.hold_ms * 1_000_000:
            return state.beam.target
        state.source_id = ""
        return None

    def _publish_ready(self, stream_id: str, state: StreamState, end_of_stream: bool) -> None:
        while state.chunks and len(state.ready) >= state.chunks[0].frames:
            chunk = state.chunks.pop(0)
            samples, state.ready = state.ready[:chunk.frames], state.ready[chunk.frames:]
            last = end_of_stream and not state.chunks
            pcm = np.clip(np.round(samples * 32768), -32768, 32767).astype(np.int16)
            self.publish(self.settings.output_topic, pcm, chunk.start_ns, chunk.end_ns, stream_id=chunk.stream_id,
                         end_of_stream=last)
            if last:
                self._ended_on_chunk.add(chunk.stream_id)
        if end_of_stream:
            self.streams.pop(stream_id)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if stream_id in self._ended_on_chunk:
            self._ended_on_chunk.discard(stream_id)
        else:  # nothing was left to carry the end: say it with an empty chunk
            super().on_end_of_stream(stream_id, audio)

"""Denoiser service: the speech the recogniser hears, with the room's noise taken out.

It reads an audio topic (``vad/speech`` by default: the vad's utterances) and publishes the same
channels, denoised by DeepFilterNet 3 (:mod:`esiaf_services.denoiser.filter`), with the same capture
times and meta (the vad's segment and utterance end, SSL directions, the stream's end) on
``denoiser/speech``. Each chunk is published once its denoised samples are complete: the model's
30 ms look-ahead and the resamplers' delay it in wall time, never in capture time; at an utterance's
end (or the stream's) the held-back samples are flushed at once, so an utterance ends as soon as the
vad ends it. Each stream has its own filters (one per channel), which go on from one utterance to
the next. An utterance whose vad went away mid-way (another publisher, or lost messages: what the
recogniser itself would see without a denoiser in between) is flushed, and the next chunk carries
``meta.broken_off``, so the recogniser closes it with a ``nothing`` instead of joining it to the next.

It also denoises a continuous topic (``beamformer/audio``): nothing there ends an utterance, and the
samples come out as the look-ahead allows. Where it stands in ``esiaf run`` and why (the vad keeps
hearing the undenoised audio): the module docstring of :mod:`esiaf.tools.cli_start` and
docs/benchmarks.md ("The denoiser").
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from esiaf.per_stream import PerStream
from esiaf.receiving import broken_off
from esiaf_services.denoiser.filter import ChannelFilter, DenoiserError, check

log = logging.getLogger(__name__)


class DenoiserSettings(ComponentSettings):
    input_topic: str = "vad/speech"
    output_topic: str = "denoiser/speech"
    sample_rate_hz: int = Field(16000, ge=8000, le=192000)
    channels: int = Field(1, ge=1, le=16)  # each denoised on its own
    # the most the noise is lowered, in dB (DeepFilterNet's attenuation limit; 100 = no limit)
    atten_lim_db: float = 100.0
    post_filter_beta: float = 0.0  # DeepFilterNet's post-filter: 0 = off, up to 0.1


@dataclass
class StreamState:
    filters: list[ChannelFilter]
    chunks: list[Audio] = field(default_factory=list)  # waiting for their denoised samples
    ready: list[np.ndarray] = field(default_factory=list)  # per channel: denoised, not yet published
    publisher: str = ""  # of the open utterance's last chunk, and its sequence number (receiving.broken_off)
    sequence: int = 0
    open: bool = False  # an utterance has begun and not ended
    broken: bool = False  # the next chunk published says the utterance before it broke off


class Denoiser(Component):
    """Takes the noise out of each channel (DeepFilterNet 3), the capture times unchanged."""

    service = "denoiser"
    kind = "other"
    Settings = DenoiserSettings
    settings: DenoiserSettings  # an instance of Settings: its fields, for type checkers

    def __init__(self, settings: DenoiserSettings):
        super().__init__(settings)
        try:
            check(settings.atten_lim_db, settings.post_filter_beta)
        except DenoiserError as exc:
            raise SetupError(f"bad denoiser settings: {exc}") from None
        self.format = AudioFormat(settings.sample_rate_hz, "int16", channels=settings.channels)
        self.add_input(settings.input_topic, self.format)
        self.add_output(settings.output_topic, self.format)
        self.streams: PerStream[StreamState] = PerStream(self._new_stream, settings.max_streams, "denoiser",
                                                         info=self.info)
        self._ended_on_chunk: set[str] = set()  # streams whose end went out with their last chunk
        self._first_filters: list[ChannelFilter] = []  # made by setup(), taken by the first stream
        self.info.update(model="DeepFilterNet3", atten_lim_db=settings.atten_lim_db)

    def _new_stream(self, _stream_id: str) -> StreamState:
        """A stream's filters: those made at start-up for the first stream, new ones (0.4 s to load the
        model) for each stream after it."""
        filters, self._first_filters = self._first_filters or self._filters(), []
        return StreamState(filters, ready=[np.zeros(0, np.float32)] * self.settings.channels)

    def _filters(self) -> list[ChannelFilter]:
        s = self.settings
        return [ChannelFilter(s.sample_rate_hz, s.atten_lim_db, s.post_filter_beta) for _ in range(s.channels)]

    def setup(self) -> None:
        self._first_filters = self._filters()  # the model loads here, not on the first stream's first chunk
        log.info("denoising model=DeepFilterNet3 channels=%d rate=%d atten_lim_db=%g", self.settings.channels,
                 self.settings.sample_rate_hz, self.settings.atten_lim_db)

    def on_audio(self, audio: Audio) -> None:
        state = self.streams.get(audio.stream_id)
        why = broken_off(state.publisher, state.sequence, audio) if state.open else ""
        if why:  # the utterance will never end as it began: its rest out, and the next chunk says so
            log.info("stream_id=%s: utterance broken off: %s", audio.stream_id, why)
            state.ready = [np.concatenate([ready, f.flush()]) for ready, f in
                           zip(state.ready, state.filters, strict=True)]
            self._publish_ready(state)
            state.broken = True
        state.publisher, state.sequence = audio.publisher, audio.sequence
        state.open = not (audio.segmentation_ended or audio.end_of_stream)
        if audio.frames:
            state.chunks.append(audio)
            samples = audio.as_float()
            state.ready = [np.concatenate([ready, f.process(samples[:, c])])
                           for c, (ready, f) in enumerate(zip(state.ready, state.filters, strict=True))]
        elif audio.segmentation_ended or audio.end_of_stream:
            state.chunks.append(audio)  # an empty chunk that carries a mark: it goes out in its turn
        if audio.segmentation_ended or audio.end_of_stream:  # nothing follows soon: the held-back samples out
            state.ready = [np.concatenate([ready, f.flush()]) for ready, f in
                           zip(state.ready, state.filters, strict=True)]
        self._publish_ready(state)
        if audio.end_of_stream:
            self.streams.pop(audio.stream_id)

    def _publish_ready(self, state: StreamState) -> None:
        """Each chunk whose denoised samples are complete, with its own times and meta, in order."""
        while state.chunks and len(state.ready[0]) >= state.chunks[0].frames:
            chunk = state.chunks.pop(0)
            samples = np.stack([ready[:chunk.frames] for ready in state.ready], axis=1)
            state.ready = [ready[chunk.frames:] for ready in state.ready]
            pcm = np.clip(np.round(samples * 32768), -32768, 32767).astype(np.int16)
            segment = chunk.meta.segment
            self.publish(self.settings.output_topic, pcm, chunk.start_ns, chunk.end_ns, stream_id=chunk.stream_id,
                         segmentation_ended=chunk.segmentation_ended,
                         segment=(segment.start_ns, segment.end_ns) if chunk.meta.HasField("segment") else None,
                         ssl_directions=chunk.ssl_directions, end_of_stream=chunk.end_of_stream,
                         broken_off=state.broken, speech_until_ns=chunk.meta.speech_until_ns)
            state.broken = False
            if chunk.end_of_stream:
                self._ended_on_chunk.add(chunk.stream_id)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if stream_id in self._ended_on_chunk:
            self._ended_on_chunk.discard(stream_id)
        else:  # nothing was left to carry the end: say it with an empty chunk
            super().on_end_of_stream(stream_id, audio)

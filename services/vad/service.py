"""VAD service: forwards only speech audio and publishes a VAD result per segment."""
from __future__ import annotations

import logging

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from services.vad.segmenter import Segmenter, SegmenterParams, level_db

log = logging.getLogger(__name__)


class VadSettings(ComponentSettings):
    input_topic: str = "grabber/audio"
    output_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    channels: int = 1
    db_min: float = 65.0  # Pepper: 70
    db_keep_alive: float = 60.0  # Pepper: 65
    keep_alive_ms: float = 400.0
    max_ms: float = 8000.0
    pre_roll_ms: float = 250.0


class Vad(Component):
    """Double-threshold voice activity detector (ESIAF's original segmenter)."""

    service = "vad"
    designation = "vad"
    Settings = VadSettings

    def __init__(self, settings: VadSettings):
        super().__init__(settings)
        try:
            fmt = AudioFormat(settings.sample_rate_hz, settings.sample_type, channels=settings.channels)
            self.params = SegmenterParams(settings.db_min, settings.db_keep_alive, settings.keep_alive_ms,
                                          settings.max_ms, settings.pre_roll_ms)
        except ValueError as exc:
            raise SetupError(f"bad VAD settings: {exc}") from None
        self.add_input(settings.input_topic, fmt)
        self.add_output(settings.output_topic, fmt)
        self.segmenters: dict[str, Segmenter[Audio]] = {}  # per stream
        self.segments = 0
        self._ended_on_chunk: set[str] = set()  # streams whose end was forwarded with their last segment

    def on_audio(self, audio: Audio) -> None:
        segmenter = self.segmenters.setdefault(audio.stream_id, Segmenter(self.params))
        level = level_db(audio.peak()) if audio.frames else float("-inf")
        for forward in segmenter.process(audio, audio.start_ns, audio.end_ns, level,
                                         force_end=audio.end_of_stream):
            chunk = forward.item
            end_of_stream = forward.ended and chunk.end_of_stream
            self.forward(self.settings.output_topic, chunk, segmentation_ended=forward.ended,
                         segment=forward.segment, end_of_stream=end_of_stream)
            if end_of_stream:
                self._ended_on_chunk.add(chunk.stream_id)
            if forward.ended:
                self.segments += 1
                self.info["segments"] = self.segments
                self.emit("vad", forward.segment, stream_id=chunk.stream_id, vad={"probability": 1.0})
                log.info("segment stream_id=%s start_ns=%d end_ns=%d", chunk.stream_id, *forward.segment)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        self.segmenters.pop(stream_id, None)
        if stream_id in self._ended_on_chunk:
            self._ended_on_chunk.discard(stream_id)
        else:  # no segment was open: tell consumers with an empty chunk
            super().on_end_of_stream(stream_id, audio)

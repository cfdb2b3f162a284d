"""Channel splitter: one multi-channel topic in, one mono topic per selected channel out.

Channel counts are never converted on a topic, so a 4-channel array feeds both
SSL (all channels) and a mono recogniser through this component. Output
``splitter/ch{i}`` carries input channel ``i`` (0-based) in the input's rate and
sample type, with the input's capture times and meta (segment, SSL directions,
end of stream).
"""
from __future__ import annotations

import logging
from typing import Any, ClassVar

from pydantic import Field

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from esiaf.api_client import declared_format

log = logging.getLogger(__name__)


class SplitterSettings(ComponentSettings):
    input_topic: str = "grabber/audio"
    channels: list[int] = Field(default_factory=list)  # input channels to publish (0-based); empty = all
    input_channels: int = 0  # 0 = as declared by the input topic's producer (asked from the orchestrator)
    sample_rate_hz: int = 16000  # with input_channels: the input's rate
    sample_type: str = "int16"  # with input_channels: the input's sample type


def output_topic(channel: int) -> str:
    return f"splitter/ch{channel}"


class Splitter(Component):
    """Splits a multi-channel topic into mono topics splitter/ch{i}."""

    service = "splitter"
    kind = "other"
    Settings = SplitterSettings
    settings: SplitterSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {
        "input_topic": "multi-channel topic to split",
        "input_channels": "channel count of the input (default: as its producer declares)"}

    def setup(self) -> None:
        s = self.settings
        if s.input_channels:
            try:
                fmt = AudioFormat(s.sample_rate_hz, s.sample_type, channels=s.input_channels)
            except ValueError as exc:
                raise SetupError(f"bad splitter input format: {exc}") from None
        else:
            declared = declared_format(s.orchestrator_url, s.input_topic, s.register_timeout_s, lambda: self.stopping)
            if declared is None:
                raise SetupError(f"no producer of {s.input_topic!r} registered with {s.orchestrator_url} within "
                                 f"{s.register_timeout_s:g} s; start it first or set input_channels")
            fmt = AudioFormat.from_dict(declared)
        wrong = sorted({c for c in s.channels if not 0 <= c < fmt.channels})
        if wrong:
            raise SetupError(f"channels {wrong} do not exist: {s.input_topic!r} has {fmt.channels} "
                             f"(0 to {fmt.channels - 1})")
        self.selected = sorted(set(s.channels)) or list(range(fmt.channels))
        mono = AudioFormat(fmt.sample_rate_hz, fmt.sample_type, fmt.endianness, channels=1)
        self.add_input(s.input_topic, fmt)
        for channel in self.selected:
            self.add_output(output_topic(channel), mono)
        log.info("splitting topic=%s format=%s channels=%s", s.input_topic, fmt, self.selected)

    def on_audio(self, audio: Audio) -> None:
        segment = audio.meta.segment
        meta: dict[str, Any] = dict(stream_id=audio.stream_id, segmentation_ended=audio.segmentation_ended,
                    segment=(segment.start_ns, segment.end_ns) if audio.meta.HasField("segment") else None,
                    ssl_directions=audio.ssl_directions, end_of_stream=audio.end_of_stream)
        samples = audio.samples
        for channel in self.selected:
            self.publish(output_topic(channel), samples[:, channel], audio.start_ns, audio.end_ns, **meta)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """Already passed on with the last chunk by on_audio."""

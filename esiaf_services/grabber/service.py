"""Grabber service: plays a file into the pipeline or captures from an ALSA device.

Capture timestamps come from sample counts: the stream's origin is the wall
clock when capture starts, and every chunk is stamped origin + samples / rate.
Played in real time, a chunk is published when its last sample would have been
captured; ``fast`` plays as fast as the pipeline takes it.

The grabber can host guests (``guests``, esiaf/hosting.py): ``esiaf run --vad-in-grabber`` runs
the vad in its process, which then takes every chunk published here without a ZeroMQ hop.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import ClassVar

from esiaf import AudioFormat, Component, SampleClock, SetupError
from esiaf.hosting import HostSettings
from esiaf.tools.mcap_replay import McapSource
from esiaf_services.grabber.sources import AlsaSource, FileSource, open_file

log = logging.getLogger(__name__)


class GrabberSettings(HostSettings):
    input: str = ""  # a sound file, .raw/.pcm file or .mcap recording; empty = live capture from `device`
    input_stream: str = ""  # of an .mcap recording: the recorded stream played ("" the first recorded)
    device: str = ""  # ALSA device name for live capture
    topic: str = "grabber/audio"
    # the transport chunk, files and live capture (the ALSA period) alike, chosen by measurement (docs/
    # benchmarks.md): 50 ms costs the framework 37 % less CPU than 20 ms (bench/framework.py), and the RoboCup
    # harness the same questions, since the vad decides per 32 ms window whatever the chunk
    chunk_ms: float = 50.0
    fast: bool = False  # play files as fast as possible instead of in real time
    # format of raw files and of live capture
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    channels: int = 1
    wait_for_subscribers: int = 0  # before playing, wait until the topic has this many subscribers
    wait_topic: str = ""  # ... that topic: "" is `topic`; a guest's output (vad/speech of a hosted vad) too
    wait_timeout_s: float = 30.0


class Grabber(Component):
    """Plays a file or captures an ALSA device into an audio topic."""

    service = "grabber"
    kind = "other"
    Settings = GrabberSettings
    settings: GrabberSettings  # an instance of Settings: its fields, for type checkers

    options: ClassVar[dict[str, str]] = {"input": "sound file to play (WAV, FLAC, ..., headerless .raw) or an "
                                                  ".mcap recording (its audio)",
                                         "device": "ALSA capture device (see arecord -L)",
                                         "fast": "play as fast as possible"}

    def __init__(self, settings: GrabberSettings):
        super().__init__(settings)
        if bool(settings.input) == bool(settings.device):
            raise SetupError("give exactly one of an input file (--input) or an ALSA device (--device)")
        if settings.chunk_ms <= 0:
            raise SetupError(f"chunk_ms must be positive, not {settings.chunk_ms}")
        try:
            self.raw_format = AudioFormat(settings.sample_rate_hz, settings.sample_type, channels=settings.channels)
        except ValueError as exc:
            raise SetupError(f"bad capture format: {exc}") from None
        self.source: FileSource | McapSource | AlsaSource | None = None
        if settings.input:  # open early: a bad file fails before registration
            self.source = open_file(Path(settings.input), self.raw_format, settings.chunk_ms,
                                    settings.input_stream or None)
            self.add_output(settings.topic, self.source.format)
        else:
            self.add_output(settings.topic, self.raw_format)

    def setup(self) -> None:
        if self.settings.device:
            self.source = AlsaSource(self.settings.device, self.raw_format, self.settings.chunk_ms)

    def produce(self) -> None:
        s = self.settings
        waited = s.wait_topic or s.topic
        if not self.context.publishes(waited):
            raise SetupError(f"wait_topic {waited} is published neither by the grabber nor by a guest")
        if s.wait_for_subscribers and not self.wait_for_subscribers(waited, s.wait_for_subscribers,
                                                                     s.wait_timeout_s) and not self.stopping:
            log.warning("topic=%s has fewer than %d subscribers after %g s; playing anyway",
                        waited, s.wait_for_subscribers, s.wait_timeout_s)
        source = self.source
        assert source is not None  # __init__ opens a file, setup() a device
        fmt = source.format
        live = isinstance(source, AlsaSource)
        chunk_ns = fmt.duration_ns(source.chunk_frames)
        origin_ns = self.clock_ns() - (chunk_ns if live else 0)
        started = time.monotonic()
        clock = SampleClock(origin_ns, fmt.sample_rate_hz)
        self.info.update(stream_start_ns=origin_ns, input=s.input or s.device, played_s=0.0,
                         duration_s=getattr(self.source, "total_frames", 0) / fmt.sample_rate_hz or None)
        self.announce_stream(origin_ns, input=s.input or s.device, format=fmt.to_dict(), chunk_ms=s.chunk_ms,
                             realtime=not s.fast or live)  # a --fast replay's capture times run ahead of the clock
        log.info("playing source=%s format=%s chunk_ms=%g realtime=%s", s.input or s.device, fmt, s.chunk_ms,
                 not (s.fast or live))
        overruns = 0
        total_frames = getattr(self.source, "total_frames", None)
        ended = False
        for samples in source.chunks():
            if isinstance(source, AlsaSource) and source.overruns != overruns:  # audio was lost: re-anchor
                overruns = source.overruns
                clock = SampleClock(self.clock_ns() - chunk_ns, fmt.sample_rate_hz)
            start_ns, end_ns = clock.advance(len(samples))
            if not (s.fast or live):
                self.sleep_until(started + (end_ns - origin_ns) / 1e9)
            if self.stopping:
                break
            ended = total_frames is not None and clock.frames >= total_frames
            self.publish(s.topic, samples, start_ns, end_ns, end_of_stream=ended)
            self.info["played_s"] = clock.frames / fmt.sample_rate_hz  # reported with heartbeats: progress
        if not ended:  # stopped, or the source ran dry early: tell consumers the stream is over
            now_ns = clock.time_at(clock.frames)
            self.publish(s.topic, b"", now_ns, now_ns, end_of_stream=True)
        log.info("played source=%s seconds=%.2f", s.input or s.device, clock.frames / fmt.sample_rate_hz)

    def teardown(self) -> None:
        if isinstance(self.source, AlsaSource):
            self.source.close()

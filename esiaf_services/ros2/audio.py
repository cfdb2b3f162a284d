"""The voices' audio: what the beamformer (steered at the talker) sent, kept by capture time for each
stream, so that a fused utterance's span can be cut out of it and published on
``/humans/voices/<id>/audio`` once the fused result names the voice.

:class:`AudioBuffer` is the store (bounded: per stream, by capture seconds and by bytes; streams, the
most recently heard ``max_streams``); :class:`VoiceAudio` is the SDK consumer that fills it from the
audio topic (``audio_topic``), in the format the bridge publishes: mono, signed 16 bit little endian,
``audio_sample_rate_hz``.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

from esiaf.audio import Audio
from esiaf.component import Component
from esiaf.formats import AudioFormat
from esiaf.per_stream import PerStream
from esiaf.settings import ComponentSettings

NS = 1_000_000_000
SAMPLE_BYTES = 2  # int16


@dataclass(frozen=True)
class Chunk:
    start_ns: int
    end_ns: int
    pcm: bytes  # mono int16


class StreamAudio:
    """One stream's latest chunks, in capture order."""

    def __init__(self) -> None:
        self.chunks: deque[Chunk] = deque()
        self.bytes = 0


class AudioBuffer:
    """Each stream's latest ``keep_s`` seconds of mono int16 audio by capture time. Thread-safe: the
    SDK's loop adds, the bridge's websocket loop cuts."""

    def __init__(self, sample_rate_hz: int, keep_s: float, max_streams: int) -> None:
        self.sample_rate_hz = sample_rate_hz
        self.keep_ns = int(keep_s * NS)
        self.max_bytes = int(keep_s * sample_rate_hz) * SAMPLE_BYTES  # a chunk's span may lie: bytes bound it too
        self.restarted = 0  # chunks that went back in capture time: the stream's audio was started afresh
        self._streams: PerStream[StreamAudio] = PerStream(lambda _: StreamAudio(), max_streams, "voice audio")
        self._lock = threading.Lock()

    def add(self, stream_id: str, start_ns: int, end_ns: int, pcm: bytes) -> None:
        with self._lock:
            stream = self._streams.get(stream_id)
            if stream.chunks and start_ns < stream.chunks[-1].end_ns:  # overlaps what is kept (a restarted
                stream.chunks.clear()                                   # producer, a replayed stream)
                stream.bytes = 0
                self.restarted += 1
            stream.chunks.append(Chunk(start_ns, end_ns, pcm))
            stream.bytes += len(pcm)
            while stream.chunks and (end_ns - stream.chunks[0].start_ns > self.keep_ns
                                     or stream.bytes > self.max_bytes):
                stream.bytes -= len(stream.chunks.popleft().pcm)

    @property
    def kept_bytes(self) -> int:
        """The audio held, every stream's."""
        with self._lock:
            return sum(stream.bytes for stream in self._streams.values())

    def reached_ns(self, stream_id: str) -> int:
        """The capture time the stream's audio has reached (0: none heard)."""
        with self._lock:
            if stream_id not in self._streams or not self._streams[stream_id].chunks:
                return 0
            return self._streams[stream_id].chunks[-1].end_ns

    def cut(self, stream_id: str, start_ns: int, end_ns: int) -> bytes:
        """The samples kept between ``start_ns`` and ``end_ns`` (capture time), in order; a part no
        longer kept (or never heard) is left out."""
        with self._lock:
            if stream_id not in self._streams:
                return b""
            parts = []
            for chunk in self._streams[stream_id].chunks:
                if chunk.end_ns <= start_ns or chunk.start_ns >= end_ns:
                    continue
                frames = len(chunk.pcm) // SAMPLE_BYTES
                first = min(max(0, (start_ns - chunk.start_ns) * self.sample_rate_hz // NS), frames)
                last = min(max(0, -(-(end_ns - chunk.start_ns) * self.sample_rate_hz // NS)), frames)
                parts.append(chunk.pcm[first * SAMPLE_BYTES:last * SAMPLE_BYTES])
            return b"".join(parts)


class VoiceAudio(Component):
    """The ros2 service's audio input: the audio topic's chunks into an :class:`AudioBuffer`."""

    service = "ros2"
    kind = "other"

    def __init__(self, settings: ComponentSettings, topic: str, buffer: AudioBuffer) -> None:
        super().__init__(settings)
        self.buffer = buffer
        self.add_input(topic, AudioFormat(buffer.sample_rate_hz, "int16", channels=1))

    def on_audio(self, audio: Audio) -> None:
        if audio.frames:
            self.buffer.add(audio.stream_id, audio.start_ns, audio.end_ns, audio.payload)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """A consumer with no outputs: nothing to pass on (the stream's audio stays for its last fused results)."""

    def refresh_info(self) -> None:
        self.info.update(audio_kept_bytes=self.buffer.kept_bytes, audio_restarted=self.buffer.restarted)

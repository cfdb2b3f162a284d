"""Reading a recording back (docs/recording.md): whether a file is a whole ESIAF MCAP, the audio it
holds as a grabber plays it (``esiaf run --input session.mcap``), and its fused results.

Every stream recorded on the replayed audio topic (``grabber/audio`` if it is there, else the first
audio topic recorded) is replayed, each by a grabber of its own as a stream of its own (``esiaf run``
gives each recorded stream its own input). A grabber plays one recorded stream's chunks as they
were, stamped with today's capture times, in real time or as fast as the pipeline takes them
(``--fast``)."""
from __future__ import annotations

import functools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from esiaf.formats import AudioFormat, decode
from esiaf.proto import esiaf_pb2 as pb

MAGIC = b"\x89MCAP0\r\n"
AUDIO_SCHEMA = pb.AugmentedAudio.DESCRIPTOR.full_name
FUSED_SCHEMA = pb.FusedResult.DESCRIPTOR.full_name
PREFERRED_TOPIC = "grabber/audio"


class SessionError(Exception):
    """The file is no recording that can be replayed: one line saying why."""


def is_mcap(path: Path) -> bool:
    """Whether ``path`` is meant as an MCAP file: its name ends in .mcap, or it starts with MCAP's magic."""
    if path.suffix.lower() == ".mcap":
        return True
    try:
        with path.open("rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _reader(handle: IO[bytes], path: Path) -> Any:
    """A seeking reader of a whole MCAP file (its footer and summary there), or SessionError."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    if handle.read(len(MAGIC)) != MAGIC:
        raise SessionError(f"{path} is not an MCAP file (it does not start with MCAP's magic bytes)")
    handle.seek(-len(MAGIC), 2)
    if handle.read(len(MAGIC)) != MAGIC:
        raise SessionError(f"{path} is a truncated MCAP file (no end magic: the recording was cut off)")
    handle.seek(0)
    reader = make_reader(handle)
    try:
        if reader.get_summary() is None:
            raise SessionError(f"{path} is an MCAP file without a summary (not finished by its writer)")
    except (McapError, EOFError, ValueError, OSError) as exc:
        raise SessionError(f"{path} is a damaged MCAP file: {exc}") from None
    return reader


def _messages(path: Path, schema: str, topic: str | None = None) -> Iterator[tuple[str, bytes]]:
    """(topic, data) of every message of ``schema`` (on ``topic``, if given), in log time order."""
    from mcap.exceptions import McapError
    try:
        with path.open("rb") as handle:
            reader = _reader(handle, path)
            try:
                for found, channel, message in reader.iter_messages(topics=[topic] if topic else None):
                    if found is not None and found.name == schema:
                        yield channel.topic, message.data
            except (McapError, EOFError, ValueError) as exc:
                raise SessionError(f"{path} is a damaged MCAP file: {exc}") from None
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None


def audio_topic(path: Path) -> str:
    """The audio topic replayed: grabber/audio if recorded, else the first audio topic."""
    try:
        with path.open("rb") as handle:
            summary = _reader(handle, path).get_summary()
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None
    schemas = {schema_id: schema.name for schema_id, schema in summary.schemas.items()}
    topics = sorted(channel.topic for channel in summary.channels.values()
                    if schemas.get(channel.schema_id) == AUDIO_SCHEMA)
    if not topics:
        raise SessionError(f"{path} holds no recorded audio (no channel of {AUDIO_SCHEMA})")
    return PREFERRED_TOPIC if PREFERRED_TOPIC in topics else topics[0]


def recorded_audio(path: Path, stream_id: str | None = None) -> Iterator[pb.AugmentedAudio]:
    """The chunks of ``stream_id`` (None: the first stream) on the replayed topic, in capture order
    (empty ones left out)."""
    for _, data in _messages(path, AUDIO_SCHEMA, audio_topic(path)):
        chunk = pb.AugmentedAudio.FromString(data)
        stream_id = chunk.stream_id if stream_id is None else stream_id
        if chunk.stream_id == stream_id and chunk.payload:
            yield chunk


def stream_name(stream_id: str) -> str:
    """A stream id without the time stamp ``esiaf run`` adds (``robot1-20261127-101500`` -> ``robot1``):
    what a recorded stream and its replay share."""
    return re.sub(r"-\d{8}-\d{6}$", "", stream_id) or stream_id


def recorded_streams(path: Path) -> list[str]:
    """The streams recorded on the replayed topic, in the order of their first chunk with audio."""
    try:
        stat = path.stat()
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None
    return list(_recorded_streams(path.absolute(), stat.st_size, stat.st_mtime_ns))


@functools.lru_cache(maxsize=8)
def _recorded_streams(path: Path, size: int, mtime_ns: int) -> tuple[str, ...]:
    streams: dict[str, None] = {}
    for _, data in _messages(path, AUDIO_SCHEMA, audio_topic(path)):
        chunk = pb.AugmentedAudio.FromString(data)
        if chunk.payload:
            streams.setdefault(chunk.stream_id)
    if not streams:
        raise SessionError(f"{path} holds no audio to replay")
    return tuple(streams)


@dataclass(frozen=True)
class SessionInfo:
    """What a replay needs to know before it starts."""
    format: AudioFormat
    frames: int
    stream_id: str
    start_ns: int  # the capture time of the recorded stream's first sample


def check_session(path: Path, stream_id: str | None = None) -> SessionInfo:
    """Reads a recorded stream (None: the first) once: its audio's format and length; SessionError if
    it cannot be replayed. Asked again of the same file unchanged (esiaf run checks its inputs twice),
    it answers from memory."""
    try:
        stat = path.stat()
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None
    return _check_session(path.absolute(), stream_id, stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=32)
def _check_session(path: Path, wanted: str | None, size: int, mtime_ns: int) -> SessionInfo:
    fmt: AudioFormat | None = None
    frames, stream_id, start_ns = 0, "", 0
    for chunk in recorded_audio(path, wanted):
        if fmt is None:
            fmt, stream_id, start_ns = AudioFormat.from_proto(chunk.format), chunk.stream_id, chunk.start_ns
        elif AudioFormat.from_proto(chunk.format) != fmt:
            raise SessionError(f"{path}: stream {stream_id}'s audio changes format mid-recording; a replay plays one")
        frames += fmt.frames_in(chunk.payload)
    if fmt is None or not frames:
        raise SessionError(f"{path} holds no audio to replay" + (f" of stream {wanted}" if wanted else ""))
    return SessionInfo(fmt, frames, stream_id, start_ns)


class McapSource:
    """The grabber's source for a recording: one recorded stream's audio chunks (None: the first
    stream's) as they were recorded."""

    def __init__(self, path: Path, stream_id: str | None = None) -> None:
        self.path = path
        info = check_session(path, stream_id)
        self.stream_id = info.stream_id
        self.format = info.format
        self.total_frames = info.frames
        first = next(recorded_audio(path, self.stream_id))
        self.chunk_frames = max(1, self.format.frames_in(first.payload))

    def chunks(self) -> Iterator[np.ndarray]:
        for chunk in recorded_audio(self.path, self.stream_id):
            yield decode(chunk.payload, self.format)


def recorded_fused(path: Path) -> list[pb.FusedResult]:
    """The recording's fused results, each at its latest revision, by window start."""
    latest: dict[int, pb.FusedResult] = {}
    for _, data in _messages(path, FUSED_SCHEMA):
        fused = pb.FusedResult.FromString(data)
        if fused.id not in latest or fused.revision >= latest[fused.id].revision:
            latest[fused.id] = fused
    return sorted(latest.values(), key=lambda fused: fused.anchor.span.start_ns)


def stream_start_ns(path: Path, stream_id: str | None = None) -> int:
    """The capture time of a replayed stream's first recorded sample: the origin its fused results are diffed from."""
    return check_session(path, stream_id).start_ns

"""A component's input side: what peers send, checked, counted and converted before any handler sees it.

Every audio message is bounded (docs/reliability.md): its size, rate, channels, length and
capture times. One refused is counted per reason and per publisher and logged (the first and
every 100th), never fatal. Sequence gaps are counted as lost messages. Each publisher on each
topic has its own conversion state (esiaf/links.py); only the most recently heard
MAX_PUBLISHERS are kept, so forged publisher names cannot grow the process.
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass

from esiaf.audio import Audio
from esiaf.formats import AudioFormat, FormatError
from esiaf.frames import topic_name
from esiaf.links import InputLink
from esiaf.proto import esiaf_pb2 as pb

log = logging.getLogger("esiaf.component")  # the component's log, as it was before this module was split off

# Bounds on what a peer may send (docs/reliability.md)
MAX_MESSAGE_BYTES = 16 * 1024 * 1024  # one AugmentedAudio message
MAX_CHUNK_S = 10.0  # audio in one message
MIN_RATE_HZ, MAX_RATE_HZ = 8_000, 192_000
MAX_CHANNELS = 64
MAX_PUBLISHERS = 256  # publishers (topic, instance) whose state is kept
MAX_TIME_NS = 2**62  # capture times after 2116 are refused: sums never overflow


def check_audio(audio: Audio) -> None:
    """Raises ValueError if a received chunk is out of bounds: rate, channels, size, times."""
    fmt = audio.format
    if not MIN_RATE_HZ <= fmt.sample_rate_hz <= MAX_RATE_HZ:
        raise ValueError(f"sample rate {fmt.sample_rate_hz} Hz outside {MIN_RATE_HZ}..{MAX_RATE_HZ}")
    if fmt.channels > MAX_CHANNELS:
        raise ValueError(f"{fmt.channels} channels, more than {MAX_CHANNELS}")
    frames = fmt.frames_in(audio.payload)  # FormatError (a ValueError) if not whole frames
    if frames > MAX_CHUNK_S * fmt.sample_rate_hz:
        raise ValueError(f"{frames / fmt.sample_rate_hz:.1f} s of audio in one message, more than {MAX_CHUNK_S:g}")
    if not 0 <= audio.start_ns <= audio.end_ns < MAX_TIME_NS:
        raise ValueError(f"capture span {audio.start_ns}..{audio.end_ns} is not ordered within 1970..2116")
    if len(audio.stream_id) > 200 or len(audio.publisher) > 200:
        raise ValueError("stream or publisher name over 200 characters")


def broken_off(publisher: str, sequence: int, audio: Audio) -> str:
    """Why ``audio`` does not continue an utterance whose last chunk came from ``publisher`` with
    ``sequence`` ("" if it does): another publisher (its VAD was restarted, so the utterance's end will
    never come), messages lost in between, or a component in between (the denoiser) says its own input
    broke off (``meta.broken_off``). An analyser then closes the utterance with a ``nothing``
    rather than take it on with what follows, which would put its words on the next one's span."""
    if audio.publisher != publisher:
        return f"its VAD went away mid-utterance ({publisher} gave way to {audio.publisher})"
    if audio.sequence > sequence + 1:
        return f"{audio.sequence - sequence - 1} messages of its audio were lost"
    if audio.meta.broken_off:
        return f"{audio.publisher} says its input broke off mid-utterance (its VAD went away, or audio was lost)"
    return ""


@dataclass
class InputStats:
    received: int = 0
    lost: int = 0  # sequence numbers skipped: messages that never arrived
    bad: int = 0  # messages that could not be used (undecodable, wrong format, handler error)
    # the input's queue depth: the most messages found waiting behind another at once (taken back to
    # back, without waiting) since the last heartbeat; 0 while the component keeps up
    queued: int = 0

    def took_back_to_back(self, count: int) -> None:
        """``count`` messages were taken without waiting: all but the first had queued."""
        self.queued = max(self.queued, count - 1)

    def heartbeat(self) -> dict[str, int]:
        """The counts for a heartbeat; the queue depth starts again for the next one."""
        counts, self.queued = asdict(self), 0
        return counts


class Replays:
    """The streams that are replays (``meta.replay``: played faster than real time, ``esiaf run --fast``),
    as the audio received says, or as a source that announced its own stream not real time says;
    the most recent MAX_STREAMS. A replay's audio and results wait for their consumers instead of
    being dropped at the high-water mark (esiaf/transport.py); live audio never waits. A stream
    heard live again is live again."""

    MAX_STREAMS = 1024

    def __init__(self) -> None:
        self._streams: OrderedDict[str, None] = OrderedDict()  # oldest first

    def note(self, stream_id: str, replay: bool) -> None:
        """Remembers whether ``stream_id`` is a replay."""
        if not replay:
            self._streams.pop(stream_id, None)
            return
        self._streams[stream_id] = None
        self._streams.move_to_end(stream_id)
        while len(self._streams) > self.MAX_STREAMS:
            self._streams.popitem(last=False)

    def __contains__(self, stream_id: object) -> bool:
        return stream_id in self._streams

    def __len__(self) -> int:
        return len(self._streams)

    def mark(self, message: pb.AugmentedAudio) -> bool:
        """Marks an outgoing message of a replay as such (every message: resampler tails too); True if it is."""
        if message.stream_id not in self._streams:
            return False
        message.meta.replay = True
        return True


@dataclass
class Received:
    """A message taken: its topic, the topic's counters, the message and the chunks it gives."""
    topic: str
    stats: InputStats
    audio: Audio
    chunks: list[Audio]


class Receiver:
    """The input side of one component: its topics' counters, refusals and per-publisher state."""

    def __init__(self, inputs: dict[str, AudioFormat], on_loss: Callable[[], None]):
        self.inputs = inputs  # the component's declared inputs (the same dict: add_input() fills it)
        self.stats: dict[str, InputStats] = {}
        self.refused: dict[str, int] = {}  # audio messages refused, by reason
        self.refused_by_publisher: dict[str, int] = {}  # ... by publisher (the most recent ones)
        # per topic, publisher and stream: a publisher numbers each stream apart, as a consumer that
        # serves some of its streams (a replica) receives only those
        self.links: dict[tuple[str, str, str], InputLink] = {}
        self.last_seen: dict[tuple[str, str, str], int] = {}  # the last sequence number
        self._on_loss = on_loss  # called when messages were lost
        self.replays = Replays()  # the streams that are replays: their publications wait for consumers

    def receive(self, frames: list[bytes]) -> Received | None:
        """The chunks a message gives, in the declared format; None if the topic is not one of the
        inputs, or if the message is refused (counted and logged)."""
        topic = topic_name(frames[0]) if frames else ""
        stats = self.stats.get(topic)
        if stats is None:
            return None  # a topic this component did not subscribe to (a SUB filters by prefix)
        if len(frames) != 2:
            self.refuse(stats, "frames", "", f"{len(frames)} frames, not 2")
            return None
        try:
            if len(frames[1]) > MAX_MESSAGE_BYTES:
                raise ValueError(f"message of {len(frames[1])} bytes, more than {MAX_MESSAGE_BYTES}")
            audio = Audio.from_message(pb.AugmentedAudio.FromString(frames[1]))
            check_audio(audio)
        except Exception as exc:  # a peer's bytes: DecodeError, FormatError, bounds... never fatal
            self.refuse(stats, "undecodable", "", f"{type(exc).__name__}: {exc}")
            return None
        stats.received += 1
        self.replays.note(audio.stream_id, audio.meta.replay)
        self.count_gap(audio, stats)
        link = self.link(topic, audio.publisher, audio.stream_id)
        try:
            chunks = link.receive(audio)
        except FormatError as exc:  # a channel count this component does not take
            self.refuse(stats, "format", audio.publisher, str(exc))
            return None
        return Received(topic, stats, audio, chunks)

    def link(self, topic: str, publisher: str, stream_id: str) -> InputLink:
        """The conversion state of one publisher on one topic; the least recently heard of more
        than MAX_PUBLISHERS are forgotten (10,000 forged names must not grow the process)."""
        key = (topic, publisher, stream_id)
        link = self.links.pop(key, None) or InputLink(self.inputs[topic])
        self.links[key] = link  # most recent last
        while len(self.links) > MAX_PUBLISHERS:
            oldest = next(iter(self.links))
            del self.links[oldest]
            self.last_seen.pop(oldest, None)
        return link

    def refuse(self, stats: InputStats, reason: str, publisher: str, detail: str) -> None:
        """Counts a refused message (per reason, per publisher) and logs the first and every 100th."""
        stats.bad += 1
        self.refused[reason] = self.refused.get(reason, 0) + 1
        if publisher:
            by_peer = self.refused_by_publisher
            by_peer[publisher] = by_peer.pop(publisher, 0) + 1
            if len(by_peer) > MAX_PUBLISHERS:
                del by_peer[next(iter(by_peer))]
        if self.refused[reason] == 1 or self.refused[reason] % 100 == 0:
            log.error("refused audio reason=%s publisher=%s count=%d detail=%.300s",
                      reason, publisher or "?", self.refused[reason], detail)

    def count_gap(self, audio: Audio, stats: InputStats) -> None:
        key = (audio.topic, audio.publisher, audio.stream_id)
        last = self.last_seen.get(key)
        if last is not None and audio.sequence > last + 1:
            missing = audio.sequence - last - 1
            stats.lost += missing
            log.warning("lost audio topic=%s publisher=%s stream_id=%s missing=%d lost_total=%d",
                        audio.topic, audio.publisher, audio.stream_id, missing, stats.lost)
            self._on_loss()
        elif last is None and audio.sequence > 1:
            log.info("joined topic=%s publisher=%s stream_id=%s at sequence=%d",
                     audio.topic, audio.publisher, audio.stream_id, audio.sequence)
        self.last_seen[key] = audio.sequence

"""Format conversion at both ends of a topic, as the component SDK uses it.

The orchestrator assigns each topic an internal (wire) format; each component
declared an external format per topic (the one its code works in).

- An :class:`OutputLink` (one per output topic, with a resampler per stream)
  converts what the component publishes to the assigned format. A new assignment takes effect at the next
  published chunk, a message boundary: the old resampler's held-back tail is
  sent first as a message of its own, in the old format, so nothing is dropped
  or duplicated and sequence numbers stay contiguous (they are the
  component's, one per message).
- An :class:`InputLink` (one per input topic and publisher) converts every
  received message from the format it carries to the declared one, so a
  consumer never needs to know of a switch: messages describe themselves.
  When the incoming format changes, the old resampler's tail is put in front
  of the first converted chunk of the new format.

Either side ends a resampler stretch (and gives out its tail) on a message
marked ``segmentation_ended`` or ``end_of_stream``, and when a chunk does not
continue the previous one in capture time (a gap, lost messages, a new
stream). See docs/protocol.md, "Audio formats".
"""
from __future__ import annotations

import dataclasses
import logging
from collections import OrderedDict
from dataclasses import dataclass

from esiaf.audio import Audio
from esiaf.convert import Converted, StreamConverter
from esiaf.formats import AudioFormat, FormatError

log = logging.getLogger(__name__)


@dataclass
class OutputStats:
    published: int = 0
    dropped: int = 0  # refused at the high-water mark
    subscribers: int = 0  # subscriptions to the topic (a replica that takes some streams has one per stream)


@dataclass
class Outgoing:
    """One message to send: its wire format, converted payload and span, and whether it is the
    published chunk itself (``main``, it carries the meta) or a tail sent ahead of it."""

    format: AudioFormat
    chunk: Converted
    stream_id: str
    main: bool


class OutputLink:
    """Converts one output topic's chunks to its assigned format, with a resampler per stream: a
    producer publishing several streams on one topic (a grabber with several inputs, a replica)
    interleaves their chunks, and a stream's resampler must never see another's samples."""

    MAX_STREAMS = 1024  # resamplers kept; past it the least recently used gives out its tail and goes

    def __init__(self, topic: str, declared: AudioFormat):
        self.topic = topic
        self.declared = declared
        self.assigned = declared  # what the orchestrator wants on the wire; applied at the next chunk
        self.wire = declared  # what is sent now
        self._converters: OrderedDict[str, StreamConverter] = OrderedDict()  # per stream, oldest use first

    @property
    def converts(self) -> bool:
        return self.wire != self.declared

    def messages(self, payload: bytes, start_ns: int, end_ns: int, stream_id: str,
                 segmentation_ended: bool = False, end_of_stream: bool = False) -> list[Outgoing]:
        """What to send for one published chunk (payload in the declared format): the chunk, after
        any resampler tail that must go first (a format switch, or a gap in this stream). A chunk
        that ends a segment or the stream also carries what its resampler held back."""
        out: list[Outgoing] = []
        if self.assigned != self.wire:
            for stream in list(self._converters):
                out += self._flush(stream)
            log.info("format switch topic=%s from=%s to=%s", self.topic, self.wire, self.assigned)
            self.wire = self.assigned
        if not self.converts:
            return [*out, Outgoing(self.wire, Converted(bytes(payload), start_ns, end_ns), stream_id, main=True)]
        converter = self._converters.get(stream_id)
        if converter is None:
            while len(self._converters) >= self.MAX_STREAMS:
                out += self._flush(next(iter(self._converters)))
            converter = self._converters[stream_id] = StreamConverter(self.declared, self.wire)
        elif payload and not converter.continues(start_ns):
            out += self._flush(stream_id, keep=True)
        self._converters.move_to_end(stream_id)
        chunk = converter.convert(bytes(payload), start_ns, end_ns, last=segmentation_ended or end_of_stream)
        if end_of_stream:
            del self._converters[stream_id]
        return [*out, Outgoing(self.wire, chunk, stream_id, main=True)]

    def _flush(self, stream_id: str, keep: bool = False) -> list[Outgoing]:
        """A stream's resampler tail, as a message of its own; the resampler goes unless ``keep``."""
        converter = self._converters[stream_id] if keep else self._converters.pop(stream_id)
        tail = converter.flush()
        if tail is None or not tail.payload:
            return []
        return [Outgoing(self.wire, tail, stream_id, main=False)]


class InputLink:
    def __init__(self, declared: AudioFormat):
        self.declared = declared
        self.wire: AudioFormat | None = None  # format of the last message received
        self._converter: StreamConverter | None = None
        self._last: Audio | None = None

    def receive(self, audio: Audio) -> list[Audio]:
        """The chunks a message gives, in the declared format: usually one; a resampler tail that
        does not continue into this message (a gap) comes first as a chunk of its own."""
        if audio.format.channels != self.declared.channels:
            raise FormatError(f"message carries {audio.format}, this component takes {self.declared}; "
                              "channel counts are never converted")
        if self._converter is None and audio.format == self.wire == self.declared:
            self._last = audio  # the common case, nothing to convert: the message itself
            return [audio]
        tail = None
        if audio.format != self.wire:
            tail = self._converter.flush() if self._converter is not None else None
            self.wire = audio.format
            self._converter = StreamConverter(self.wire, self.declared) if self.wire != self.declared else None
        elif self._converter is not None and audio.frames and not self._continues(audio):
            tail = self._converter.flush()
        previous, self._last = self._last, audio
        last = audio.meta.segmentation_ended or audio.meta.end_of_stream
        if self._converter is None:
            chunk = Converted(audio.payload, audio.start_ns, audio.end_ns)
        else:
            chunk = self._converter.convert(audio.payload, audio.start_ns, audio.end_ns, last=last)
        chunks = []
        if tail is not None and tail.payload:
            assert previous is not None  # a tail is audio of an earlier message
            if self._continues(audio, previous, tail.end_ns):
                chunk = Converted(tail.payload + chunk.payload, tail.start_ns, max(chunk.end_ns, tail.end_ns))
            else:
                chunks.append(dataclasses.replace(previous, format=self.declared, payload=tail.payload,
                                                  start_ns=tail.start_ns, end_ns=tail.end_ns,
                                                  meta=type(audio.meta)()))
        chunks.append(dataclasses.replace(audio, format=self.declared, payload=chunk.payload,
                                          start_ns=chunk.start_ns, end_ns=chunk.end_ns))
        return chunks

    def _continues(self, audio: Audio, previous: Audio | None = None, end_ns: int | None = None) -> bool:
        previous = previous or self._last
        if previous is None:
            return True
        if audio.sequence != previous.sequence + 1 or audio.stream_id != previous.stream_id:
            return False
        if end_ns is None:
            assert self._converter is not None  # asked (without end_ns) only while converting
            return self._converter.continues(audio.start_ns)
        slowest = min(audio.format.sample_rate_hz, previous.format.sample_rate_hz, self.declared.sample_rate_hz)
        return abs(audio.start_ns - end_ns) <= 1_000_000_000 // slowest + 1

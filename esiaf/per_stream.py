"""A component's state per stream, bounded: the most recently heard ``max_streams`` streams.

A component keeps state for each stream it hears (a VAD's segmenter, a localiser's tracker, an
utterance's samples) and drops it when the stream ends. A stream whose source dies, or a peer that
names a new stream in every message, never sends that end: without a bound the state would grow
for as long as the process runs (so would the SDK's own record of the streams ended on some of a
component's inputs, which uses it too). :class:`PerStream` keeps the state of the most recently heard
``max_streams`` streams (the component's setting, 256 by default); past it, the least recently
heard stream's state is forgotten, counted (in the component's ``info``, so its heartbeats and
``GET /components`` show ``forgotten_streams``) and logged (the first and every 100th). Should that
stream speak again, it starts afresh: what was forgotten is lost, never what a live stream holds.

    self.segmenters = PerStream(lambda stream_id: Segmenter(...), self.settings.max_streams, "segmenter",
                                info=self.info)
    segmenter = self.segmenters.get(audio.stream_id)  # made at a stream's first chunk
    ...
    self.segmenters.pop(stream_id)  # at its end
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

log = logging.getLogger(__name__)
T = TypeVar("T")


class PerStream(Generic[T]):
    """State per stream id, made by ``make(stream_id)`` when a stream is first heard; at most
    ``max_streams`` kept, the least recently heard forgotten first."""

    def __init__(self, make: Callable[[str], T], max_streams: int = 256, what: str = "state",
                 info: dict[str, Any] | None = None):
        if max_streams < 1:
            raise ValueError(f"max_streams must be at least 1, not {max_streams}")
        self._make = make
        self.max_streams = max_streams
        self.what = what  # what the state is, for the log
        self._states: OrderedDict[str, T] = OrderedDict()  # least recently heard first
        self.forgotten = 0  # streams whose state was forgotten to keep the bound
        self._info = info  # a component's info: its "forgotten_streams" counts them (of all its PerStreams)

    def get(self, stream_id: str) -> T:
        """The stream's state, made if it has none; the stream is now the most recently heard."""
        state = self._states.get(stream_id)
        if state is not None:
            self._states.move_to_end(stream_id)
            return state
        while len(self._states) >= self.max_streams:
            oldest, _ = self._states.popitem(last=False)
            self.forgotten += 1
            if self._info is not None:
                self._info["forgotten_streams"] = self._info.get("forgotten_streams", 0) + 1
            if self.forgotten == 1 or self.forgotten % 100 == 0:
                log.warning("forgot the %s of stream_id=%s, the least recently heard of more than "
                            "max_streams=%d streams (forgotten=%d)", self.what, oldest, self.max_streams,
                            self.forgotten)
        state = self._states[stream_id] = self._make(stream_id)
        return state

    def __getitem__(self, stream_id: str) -> T:
        """The stream's state (KeyError if it has none), without making it or changing the order."""
        return self._states[stream_id]

    def pop(self, stream_id: str) -> T | None:
        """The stream's state, removed (its end); None if it had none."""
        return self._states.pop(stream_id, None)

    def __contains__(self, stream_id: object) -> bool:
        return stream_id in self._states

    def __len__(self) -> int:
        return len(self._states)

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._states))

    def values(self) -> list[T]:
        return list(self._states.values())

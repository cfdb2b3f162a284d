"""Partial results: what a recogniser has heard of an utterance still going on, passed on to the
websocket clients that asked for them (``/ws/fused?partials=1``) and nothing more.

A result of kind ``partial`` (a generic result: ``text``, ``probability``, and in its attributes the
``stable`` prefix that two successive decodes agree on) is neither stored nor fused: it is sent at
once as a ``partial`` event (docs/protocol.md, "Partial results"). Per stream one partial is open;
the next result of another kind from the same instance on that stream (its final ``speech`` result,
or its ``nothing``), or the stream's end, closes it: a ``partial`` event with ``closed: true`` is
sent, and a client drops the line it was growing (the fused result that follows replaces it). A
partial never outlives its utterance. Pure bookkeeping, bounded: at most ``MAX_OPEN`` streams
have an open partial (the least recently heard is forgotten).
"""
from __future__ import annotations

import json
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from esiaf.proto import esiaf_pb2 as pb

from .hub import Outgoing

PARTIAL_KIND = "partial"
MAX_OPEN = 10_000


@dataclass
class OpenPartial:
    instance: str
    component: str
    start_ns: int
    end_ns: int


class Partials:
    def __init__(self, max_open: int = MAX_OPEN) -> None:
        self.max_open = max_open
        self._open: OrderedDict[str, OpenPartial] = OrderedDict()  # stream -> its open partial
        self.sent = 0

    def on_partial(self, result: pb.Result, received_ns: int) -> Outgoing:
        """The event for a partial result (decoded and checked by the codec)."""
        attributes = dict(result.generic.attributes.items()) if result.generic.HasField("attributes") else {}
        stable = attributes.get("stable")
        stream = result.stream_id
        self._open.pop(stream, None)
        self._open[stream] = OpenPartial(result.instance, result.component, result.span.start_ns, result.span.end_ns)
        while len(self._open) > self.max_open:
            self._open.popitem(last=False)
        self.sent += 1
        return self._event(stream, result.component, result.instance, result.span.start_ns, result.span.end_ns,
                           text=result.generic.text, stable=stable if isinstance(stable, str) else "",
                           probability=result.generic.probability, received_ns=received_ns, closed=False)

    def on_result(self, result: pb.Result, received_ns: int) -> Outgoing | None:
        """A result of another kind: it closes its instance's open partial on that stream."""
        stream = result.stream_id
        found = self._open.get(stream)
        if found is None or found.instance != result.instance:
            return None
        del self._open[stream]
        return self._event(stream, found.component, found.instance, found.start_ns,
                           max(found.end_ns, result.span.end_ns), received_ns=received_ns, closed=True)

    def on_stream_end(self, stream: str, received_ns: int) -> Outgoing | None:
        found = self._open.pop(stream, None)
        if found is None:
            return None
        return self._event(stream, found.component, found.instance, found.start_ns, found.end_ns,
                           received_ns=received_ns, closed=True)

    @staticmethod
    def _event(stream: str, component: str, instance: str, start_ns: int, end_ns: int, *, text: str = "",
               stable: str = "", probability: float = 0.0, received_ns: int, closed: bool) -> Outgoing:
        event: dict[str, Any] = {"type": "partial", "stream_id": stream, "component": component, "instance": instance,
                                 "span": {"start_ns": start_ns, "end_ns": end_ns}, "text": text, "stable": stable,
                                 "probability": probability, "received_ns": received_ns, "closed": closed}
        return Outgoing(text=json.dumps(event, separators=(",", ":"), allow_nan=False), stream_id=stream,
                        partial=True)

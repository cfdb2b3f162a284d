"""End of stream: a stream has ended when every service with inputs that is awaited said so.

Kept by service (component name), not by instance: only the instance serving a stream sees its
end, an instance that was declared dead and came back under a new id said it under the old one,
and a service's replicas share the streams (assignment.py).
"""
from __future__ import annotations

from collections.abc import Iterable


class StreamEnds:
    def __init__(self) -> None:
        self._reported: dict[str, set[str]] = {}  # stream_id -> services that said "end"
        self._ended: set[str] = set()  # streams whose stream_end was sent

    def on_end_of_stream(self, stream_id: str, service: str) -> None:
        if stream_id not in self._ended:
            self._reported.setdefault(stream_id, set()).add(service)

    def on_result(self, stream_id: str) -> None:
        """A result after the stream ended starts it again: it must end again."""
        if stream_id in self._ended:
            self._ended.discard(stream_id)
            self._reported.pop(stream_id, None)

    def finished(self, awaited: Iterable[str]) -> list[str]:
        """Streams that have just ended, given the services awaited (those with inputs that live,
        or that may yet come back): each said "end" through one of its instances."""
        awaited = set(awaited)
        done = [stream_id for stream_id, reported in self._reported.items() if awaited <= reported]
        for stream_id in done:
            del self._reported[stream_id]
            self._ended.add(stream_id)
        return done

    def pending(self) -> dict[str, set[str]]:
        return {stream_id: set(services) for stream_id, services in self._reported.items()}

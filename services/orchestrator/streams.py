"""End of stream: a stream has ended when every live component with inputs said so."""
from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping


class StreamEnds:
    def __init__(self) -> None:
        self._reported: dict[str, set[str]] = {}  # stream_id -> component_ids that said "end"
        self._ended: set[str] = set()  # streams whose stream_end was sent

    def on_end_of_stream(self, stream_id: str, component_id: str) -> None:
        if stream_id not in self._ended:
            self._reported.setdefault(stream_id, set()).add(component_id)

    def on_result(self, stream_id: str) -> None:
        """A result after the stream ended starts it again: it must end again."""
        if stream_id in self._ended:
            self._ended.discard(stream_id)
            self._reported.pop(stream_id, None)

    def finished(self, live_with_inputs: Iterable[str],
                 predecessors: Mapping[str, Collection[str]] | None = None) -> list[str]:
        """Streams that have just ended, given the ids of the live components with inputs. A
        component counts as having said "end" when it did, or when one of its ``predecessors`` (the
        ids it had before it registered again, or the instances of its name it replaced) did."""
        predecessors = predecessors or {}
        waiting_for = [{component_id, *predecessors.get(component_id, ())} for component_id in live_with_inputs]
        done = [stream_id for stream_id, reported in self._reported.items()
                if all(ids & reported for ids in waiting_for)]
        for stream_id in done:
            del self._reported[stream_id]
            self._ended.add(stream_id)
        return done

    def pending(self) -> dict[str, set[str]]:
        return {stream_id: set(ids) for stream_id, ids in self._reported.items()}

"""The results plane's stream clocks: which component captures each announced stream (so on whose
clock its capture times are, and that clock's offset from ours), and each stream's first span (the
reference later spans must lie near). Both are bounded to the most recent ``MAX_STREAMS`` streams."""
from __future__ import annotations

from collections import OrderedDict

from ..registry.components import Registry

MAX_STREAMS = 10_000  # streams whose source and reference time are kept


class StreamClocks:
    def __init__(self, registry: Registry) -> None:
        self.registry = registry
        self.sources: OrderedDict[str, str] = OrderedDict()  # stream -> the component capturing it
        self._reference: OrderedDict[str, int] = OrderedDict()

    def announce(self, stream_id: str, source: str) -> None:
        """``source`` captures ``stream_id``: its capture times are on that component's clock."""
        self.sources[stream_id] = source
        self.sources.move_to_end(stream_id)
        while len(self.sources) > MAX_STREAMS:
            self.sources.popitem(last=False)

    def capture_offset_ns(self, stream_id: str) -> int:
        """Our clock minus the clock of the host that captures ``stream_id``: its announced source's
        offset, as that component measures it (0 while unknown)."""
        source = self.sources.get(stream_id)
        component = (self.registry.get(source) or self.registry.by_name(source)) if source else None
        return (component.clock_offset_ns or 0) if component is not None else 0

    def reference_ns(self, stream_id: str) -> int | None:
        """The first span's start of ``stream_id``, if it is among the streams kept."""
        return self._reference.get(stream_id)

    def remember(self, stream_id: str, start_ns: int) -> None:
        """The first span of each stream (the most recent MAX_STREAMS streams): later spans must
        lie near it."""
        if stream_id in self._reference:
            self._reference.move_to_end(stream_id)
            return
        self._reference[stream_id] = start_ns
        while len(self._reference) > MAX_STREAMS:
            self._reference.popitem(last=False)

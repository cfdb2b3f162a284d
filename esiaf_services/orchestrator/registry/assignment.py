"""Which instance of each service serves each stream, when a service has several.

A service is a component name; its instances are the live components of that name. While a
service has one live instance, that instance takes every stream (it subscribes to whole topics,
as it always did). Once it has several, each active stream is given to exactly one of them:

- sticky: a stream stays with its instance for as long as that instance lives;
- balanced: a new stream, or one whose instance died or left, goes to the instance serving the
  fewest active streams (the one registered first on a tie);
- an instance is told the streams it serves in its state (``"streams"``), and subscribes to
  ``topic\\0stream\\0`` for each of them instead of the whole topic, so its producers' XPUBs never
  send it another instance's streams (esiaf/transport.py).

Streams become active when announced (``PUT /streams/{id}``, what a grabber does before its first
chunk) or when a result of an unannounced one arrives; they stop being active at ``stream_end``.
Pure bookkeeping, no sockets: the registry asks :meth:`Assignments.streams_of` for each state.
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterable
from typing import Protocol

log = logging.getLogger(__name__)

MAX_ACTIVE_STREAMS = 10_000  # the oldest active stream is forgotten beyond this


class Instance(Protocol):
    component_id: str
    name: str


class Assignments:
    def __init__(self) -> None:
        self.active: OrderedDict[str, None] = OrderedDict()  # active streams, oldest first
        self._served_by: dict[str, dict[str, str]] = {}  # service -> stream -> instance id
        self.version = 0  # a new number at every change (the registry recomputes states after one)

    def add_stream(self, stream_id: str, served_by: Instance | None = None) -> bool:
        """Makes a stream active (True if it was not); ``served_by``: an instance known to serve it
        already (it sent a result of it), which keeps it."""
        if served_by is not None:
            served = self._served_by.setdefault(served_by.name, {})
            if stream_id not in served:
                served[stream_id] = served_by.component_id
                self.version += 1
        if stream_id in self.active:
            return False
        self.active[stream_id] = None
        self.version += 1
        while len(self.active) > MAX_ACTIVE_STREAMS:
            self.end_stream(next(iter(self.active)))
        return True

    def end_stream(self, stream_id: str) -> None:
        self.version += 1
        self.active.pop(stream_id, None)
        for streams in self._served_by.values():
            streams.pop(stream_id, None)

    def update(self, instances: Iterable[Instance]) -> list[tuple[str, str, str]]:
        """Serves every active stream by one live instance of each service in ``instances`` (live
        components with inputs, in registration order). Returns the (service, stream, instance)
        assignments made, moved ones included."""
        self.version += 1
        by_service: dict[str, list[str]] = {}
        for instance in instances:
            by_service.setdefault(instance.name, []).append(instance.component_id)
        for service in [s for s in self._served_by if s not in by_service]:
            del self._served_by[service]
        made = []
        for service, ids in by_service.items():
            served = self._served_by.setdefault(service, {})
            load = dict.fromkeys(ids, 0)
            for stream_id, instance_id in list(served.items()):
                if instance_id in load and stream_id in self.active:
                    load[instance_id] += 1
                else:
                    del served[stream_id]  # its instance is gone (or the stream ended): moved below
            for stream_id in self.active:
                if stream_id not in served:
                    chosen = min(ids, key=lambda i: (load[i], ids.index(i)))
                    served[stream_id] = chosen
                    load[chosen] += 1
                    made.append((service, stream_id, chosen))
        for service, stream_id, instance_id in made:
            if len(by_service[service]) > 1:
                log.info("event=stream_assigned service=%s stream_id=%s instance=%s", service, stream_id, instance_id)
        return made

    def streams_of(self, instance: Instance, instances_of_service: int) -> list[str] | None:
        """The streams ``instance`` serves, sorted; None (every stream) while it is its service's
        only instance."""
        if instances_of_service <= 1:
            return None
        served = self._served_by.get(instance.name, {})
        return sorted(s for s, i in served.items() if i == instance.component_id)

    def serving(self, service: str) -> dict[str, str]:
        """Each active stream of ``service`` and the instance serving it."""
        return dict(self._served_by.get(service, {}))

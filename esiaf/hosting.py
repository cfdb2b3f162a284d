"""Guests: the processors a component's ``guests`` setting names, run in its process.

``hosting_node(component)`` builds the node (esiaf/node.py) that runs the component first and its
guests beside it: the grabber hosting the vad (``esiaf run --vad-in-grabber``: no ZeroMQ hop and no
second process woken per chunk), emotion hosting gender (an utterance's features computed once for
both, esiaf/features.py). A guest takes each audio message through its own input side
(esiaf/receiving.py): its own counters, loss counting and conversion from the wire format to the
format it declared (a 48 kHz grabber gives a 16 kHz vad 16 kHz; channel counts are never converted,
as on the wire), exactly what it would receive over the wire.

Nothing else changes for a guest: it is built from its own class with its own settings
(``ESIAF_<SERVICE>_...``), loads its own model, registers under its own service name, instance id
and result kind, sends its own heartbeats (its own ``info``) and results, and says when a stream
has ended: the orchestrator, fusion, the dashboard and ``esiaf run`` see the same services as when
each runs in a process of its own.

A guest is named by its service (``gender``: the component of ``esiaf_services/gender/service.py``)
or as ``package.module:Class``.
"""
from __future__ import annotations

import importlib
import inspect
import logging
from typing import cast

from pydantic import Field

from esiaf.node import Node
from esiaf.processor import Processor, SetupError
from esiaf.settings import ComponentSettings, SettingsError, load_settings

log = logging.getLogger(__name__)
BUILT_IN = "esiaf_services"  # the built-in services' package: a guest named "gender" is BUILT_IN.gender.service


class HostSettings(ComponentSettings):
    # components run in this process, each its own service (e.g. ["gender"], ["vad"])
    guests: list[str] = Field(default_factory=list)


def guest_class(spec: str) -> type[Processor]:
    """The component a guest's name stands for: a built-in service's (``gender``) or ``package.module:Class``."""
    module_name, sep, class_name = spec.partition(":")
    if not sep:
        module_name = f"{BUILT_IN}.{spec}.service"
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise SetupError(f"guest {spec}: cannot import {module_name}: {exc}") from None
    if sep:
        found = [getattr(module, class_name, None)]
    else:
        found = [cls for _, cls in inspect.getmembers(module, inspect.isclass)
                 if cls.__module__ == module.__name__ and getattr(cls, "service", None) == spec]
    found = [cls for cls in found if isinstance(cls, type) and issubclass(cls, Processor)]
    if len(found) != 1:
        raise SetupError(f"guest {spec}: {module_name} has no component "
                         f"{class_name or f'whose service is {spec!r}'} (a subclass of Component or Processor)")
    return cast("type[Processor]", found[0])


def guest(spec: str) -> Processor:
    """A guest, built from its own class with its own settings (``ESIAF_<SERVICE>_...``)."""
    cls = guest_class(spec)
    try:
        settings = load_settings(cls.Settings, cls.service)
    except SettingsError as exc:
        raise SetupError(f"guest {cls.service}: {exc}") from None
    return cls(settings)


def hosting_node(processor: Processor) -> Node:
    """The node that runs ``processor`` and, beside it, the guests its ``guests`` setting names."""
    names: list[str] = list(getattr(processor.settings, "guests", []))
    guests = [guest(name) for name in names]
    if guests:
        processor.info["guests"] = [g.service for g in guests]
    return Node([processor, *guests])

"""Guests: other components run in a component's process (its ``guests`` setting).

A host (a :class:`Host`: the utterance analysers, the grabber) hands each audio message on a guest's
input topics to the guest as if it had come over the wire: every message the host receives (an
utterance analyser hosting another hears the VAD's speech once), and every message it publishes
(the grabber hosting the vad: no ZeroMQ hop and no second process woken per chunk). The guest takes
the message's bytes through its own input side (esiaf/receiving.py): its own counters, loss counting
and conversion from the wire format to the format it declared (a 48 kHz grabber gives a 16 kHz vad
16 kHz; channel counts are never converted, as on the wire), exactly what it would receive over the wire.

Nothing else changes for a guest: it is built from its own class with its own settings
(``ESIAF_<SERVICE>_...``), loads its own model, registers under its own service name, instance id
and result kind, sends its own heartbeats (its own ``info``) and results, and says when a stream
has ended: the orchestrator, fusion, the dashboard and ``esiaf run`` see the same services as when
each runs in a process of its own. It shares the host's sockets: it registers the host's audio
endpoint as its own, so a consumer of a guest's output (asr on ``vad/speech``) connects to the
host's XPUB and subscribes to the guest's topic there (the orchestrator keeps one record per
component, and two records may name one endpoint: each consumer subscribes by topic); the host
counts a subscription to a guest's topic as the guest's. A guest is not scaled apart from its host
(``--replicas`` runs the analysers apart), and an exception in its handlers is counted on its input
(``bad``) and logged, and the host goes on.

A guest is named by its service (``gender``: the component of ``esiaf_services/gender/service.py``)
or as ``package.module:Class``.
"""
from __future__ import annotations

import importlib
import inspect
import json
import logging
import queue
import threading
from typing import Any, ClassVar, cast

import zmq
from pydantic import Field

from esiaf import keys
from esiaf.component import Component, SetupError
from esiaf.control import ControlClient
from esiaf.formats import AudioFormat
from esiaf.links import OutputLink
from esiaf.settings import ComponentSettings, SettingsError, load_settings
from esiaf.transport import STATE_ADDRESS

log = logging.getLogger(__name__)
BUILT_IN = "esiaf_services"  # the built-in services' package: a guest named "gender" is BUILT_IN.gender.service


class HostSettings(ComponentSettings):
    # components run in this process, each its own service (e.g. ["gender"], ["vad"])
    guests: list[str] = Field(default_factory=list)


def guest_class(spec: str) -> type[Component]:
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
    found = [cls for cls in found if isinstance(cls, type) and issubclass(cls, Component)]
    if len(found) != 1:
        raise SetupError(f"guest {spec}: {module_name} has no component "
                         f"{class_name or f'whose service is {spec!r}'} (a subclass of Component)")
    return cast("type[Component]", found[0])


class Guest:
    """One guest: the component, and its registration with the orchestrator (its own heartbeat thread)."""

    def __init__(self, spec: str):
        cls = guest_class(spec)
        try:
            settings = load_settings(cls.Settings, cls.service)
        except SettingsError as exc:
            raise SetupError(f"guest {cls.service}: {exc}") from None
        self.analyser = cls(settings)
        self.analyser.setup()  # its model: a failure stops the host at start-up, as it would stop the guest alone
        self._context: zmq.Context | None = None
        self._state_thread: threading.Thread | None = None
        self._formats: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()  # given, not yet applied (in order)

    @property
    def name(self) -> str:
        return self.analyser.service

    def start(self, host: Host) -> None:
        """Registers the guest (after its host: it uses the host's sockets) and starts its heartbeats."""
        analyser = self.analyser
        analyser._transport = host._transport  # its audio, results and stream ends leave by the host's sockets
        analyser._output_links = {t: OutputLink(t, f) for t, f in analyser.outputs.items()}
        # its control thread hands the orchestrator's state to an inproc socket of its own context: the
        # host's sockets follow the host's state (its peers), a guest's is watched for "fatal" and formats
        self._context = zmq.Context()
        state = self._context.socket(zmq.PAIR)
        state.setsockopt(zmq.LINGER, 0)
        state.bind(STATE_ADDRESS)
        self._state_thread = threading.Thread(target=self._watch, args=(state, host), daemon=True,
                                              name=f"esiaf-guest-{self.name}")
        self._state_thread.start()
        settings = analyser.settings
        analyser.control = ControlClient(self._context, settings.orchestrator_url, analyser._registration_request(),
                                         analyser.stats, settings.register_timeout_s, "",
                                         keys.load(orchestrator=False), analyser.clock_ns)
        self._apply_formats(analyser.control.start().state().get("formats", {}))
        log.info("hosting guest=%s component_id=%s", self.name, analyser.control.component_id)

    def _watch(self, state: zmq.Socket, host: Host) -> None:
        try:
            while True:
                message = json.loads(state.recv())
                if message.get("type") == "fatal":  # the orchestrator will not have the guest: stop, as it would
                    log.error("guest %s stopping the host: %s", self.name, message.get("error"))
                    host.stop(exit_code=1)
                elif isinstance(message.get("formats"), dict):
                    self._formats.put(message["formats"])  # applied on the data thread, at the next message
        except zmq.ContextTerminated:
            pass
        finally:
            state.close()

    def _apply_formats(self, formats: dict[str, Any]) -> None:
        """The wire formats of the guest's outputs (its inputs' come with every message)."""
        for topic, fmt in formats.items():
            if (link := self.analyser._output_links.get(topic)) is not None:
                link.assigned = AudioFormat.from_dict(fmt)  # the switch happens at the next chunk

    def hear(self, frames: list[bytes]) -> None:
        """An audio message the host received or published, taken by the guest as if from the wire; a
        topic it does not take is ignored, a handler's exception counted and logged (Component._on_message)."""
        analyser = self.analyser
        while not self._formats.empty():
            self._apply_formats(self._formats.get())
        if analyser.control is not None:
            analyser.control.busy()  # its heartbeat stays fast while it works (the transport wakes the host)
        analyser._on_message(frames)

    def stop(self) -> None:
        """Unregisters it and releases its model."""
        try:
            self.analyser.teardown()
        finally:
            if self.analyser.control is not None:
                self.analyser.control.stop()
            if self._context is not None:  # ends the watching thread; on a thread of its own, so that a
                # control thread not yet finished (still registering) cannot hold the host's shutdown
                threading.Thread(target=self._context.term, daemon=True, name="esiaf-guest-term").start()
            if self._state_thread is not None:
                self._state_thread.join(timeout=3.0)


class Host(Component):
    """A component that runs the components its ``guests`` setting names in its process (see the module)."""

    Settings: ClassVar[type[ComponentSettings]] = HostSettings
    settings: HostSettings  # an instance of Settings: its fields, for type checkers

    def __init__(self, settings: HostSettings):
        super().__init__(settings)
        self.guests: list[Guest] = []  # started once registered: they register with the host's sockets
        self._guests_started = False

    def run(self) -> int:
        try:
            if self.settings.guests:  # their models load before anything registers, as the host's does
                self.guests = [Guest(spec) for spec in self.settings.guests]
                self.info["guests"] = [guest.name for guest in self.guests]
                self._check_guests()
            return super().run()
        finally:
            for guest in self.guests:
                guest.stop()

    def _check_guests(self) -> None:
        """Each guest hears one of the host's topics, and a guest with outputs needs the host's output socket."""
        for guest in self.guests:
            heard = {*self.inputs, *self.outputs}
            if not set(guest.analyser.inputs) & heard:
                raise SetupError(f"guest {guest.name} hears {', '.join(guest.analyser.inputs) or 'nothing'}, "
                                 f"and {self.service} receives or publishes only {', '.join(sorted(heard))}")
            if guest.analyser.outputs and not self.outputs:
                raise SetupError(f"guest {guest.name} publishes {', '.join(guest.analyser.outputs)}, and "
                                 f"{self.service} has no output socket to send it from")

    def _apply_state(self, state: dict[str, Any]) -> None:
        super()._apply_state(state)
        if not self._guests_started and not self.stopping:  # the first state: registered, sockets made
            self._guests_started = True
            for guest in self.guests:
                guest.start(self)

    def _on_message(self, frames: list[bytes]) -> None:
        super()._on_message(frames)
        self._hand_on(frames)  # whatever the host's handlers did with it

    def _hand_on(self, frames: list[bytes]) -> None:
        # received, or published: the frames a subscriber would take (the guest is not behind the wire's
        # high-water mark), serialised once for the wire and the guests
        for guest in self.guests:
            guest.hear(frames)

    def _on_subscription(self, topic: str, change: int) -> None:
        if (guest := self._publishing(topic)) is not None:  # on the host's socket: the guest's count
            guest._on_subscription(topic, change)
        else:
            super()._on_subscription(topic, change)

    def subscribers(self, topic: str) -> int:
        guest = self._publishing(topic)
        return super().subscribers(topic) if guest is None else guest.subscribers(topic)

    def _publishing(self, topic: str) -> Component | None:
        """The guest whose output ``topic`` is (None: the host's, or nobody's)."""
        return next((g.analyser for g in self.guests if topic in g.analyser.output_stats), None)

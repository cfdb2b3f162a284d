"""Guests: other utterance analysers run in an utterance analyser's process (its ``guests`` setting).

A host (any :class:`~esiaf.utterance.UtteranceComponent`) hears the VAD's speech once and hands
each chunk to its guests as well, so that analysers which need the same features of an utterance
(``esiaf/features.py``) compute them once, and one Python process with its libraries holds them
all. Nothing else changes for a guest: it is built from its own class with its own settings
(``ESIAF_<SERVICE>_...``), loads its own model, registers under its own service name, instance id
and result kind, sends its own heartbeats (its own ``info``) and results, and says when a stream
has ended: the orchestrator, fusion, the dashboard and ``esiaf run --without`` see the same
services as when each runs in a process of its own. It shares only the host's sockets: a guest
is not scaled apart from its host (``--replicas`` runs the analysers apart).

A guest is named by its service (``gender``: the utterance analyser of ``esiaf_services/gender/service.py``)
or as ``package.module:Class``.
"""
from __future__ import annotations

import importlib
import inspect
import json
import logging
import threading
from typing import TYPE_CHECKING, cast

import zmq

from esiaf import keys
from esiaf.audio import Audio
from esiaf.component import SetupError
from esiaf.control import ControlClient
from esiaf.settings import SettingsError, load_settings
from esiaf.transport import STATE_ADDRESS

if TYPE_CHECKING:
    from esiaf.utterance import UtteranceComponent, UtteranceSettings

log = logging.getLogger(__name__)
BUILT_IN = "esiaf_services"  # the built-in services' package: a guest named "gender" is BUILT_IN.gender.service


def guest_class(spec: str) -> type[UtteranceComponent]:
    """The utterance analyser a guest's name stands for: a built-in service's (``gender``) or
    ``package.module:Class``."""
    from esiaf.utterance import UtteranceComponent
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
    found = [cls for cls in found if isinstance(cls, type) and issubclass(cls, UtteranceComponent)]
    if len(found) != 1:
        raise SetupError(f"guest {spec}: {module_name} has no utterance analyser "
                         f"{class_name or f'whose service is {spec!r}'} (a subclass of UtteranceComponent)")
    return cast("type[UtteranceComponent]", found[0])


class Guest:
    """One guest: the analyser, and its registration with the orchestrator (its own heartbeat thread)."""

    def __init__(self, spec: str):
        cls = guest_class(spec)
        try:
            settings = load_settings(cls.Settings, cls.service)
        except SettingsError as exc:
            raise SetupError(f"guest {cls.service}: {exc}") from None
        self.analyser = cls(cast("UtteranceSettings", settings))
        self.analyser.setup()  # its model: a failure stops the host at start-up, as it would stop the guest alone
        self._context: zmq.Context | None = None
        self._state_thread: threading.Thread | None = None

    @property
    def name(self) -> str:
        return self.analyser.service

    def start(self, host: UtteranceComponent) -> None:
        """Registers the guest (after its host: it uses the host's sockets) and starts its heartbeats."""
        analyser = self.analyser
        analyser._transport = host._transport  # its results and stream ends leave by the host's socket
        # its control thread hands the orchestrator's state to an inproc socket of its own context: the
        # host's sockets follow the host's state (the same input), a guest's is only watched for "fatal"
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
        analyser.control.start()
        log.info("hosting guest=%s component_id=%s", self.name, analyser.control.component_id)

    def _watch(self, state: zmq.Socket, host: UtteranceComponent) -> None:
        try:
            while True:
                message = json.loads(state.recv())
                if message.get("type") == "fatal":  # the orchestrator will not have the guest: stop, as it would
                    log.error("guest %s stopping the host: %s", self.name, message.get("error"))
                    host.stop(exit_code=1)
        except zmq.ContextTerminated:
            pass
        finally:
            state.close()

    def dispatch(self, audio: Audio) -> None:
        """A chunk the host received, handled by the guest as if it had received it."""
        analyser = self.analyser
        if analyser.control is not None:
            analyser.control.busy()  # its heartbeat stays fast while it works (the transport wakes the host)
        if (stats := analyser.input_stats.get(audio.topic)) is not None:
            stats.received += 1
        try:
            analyser._dispatch(audio)  # the SDK's own callback order
        except Exception:  # a guest's bug must not stop the host or the other guests
            if stats is not None:
                stats.bad += 1
            log.exception("guest %s handler failed stream_id=%s start_ns=%d", self.name, audio.stream_id,
                          audio.start_ns)

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

"""A native call that holds the GIL stops the heartbeat thread too (pocketsphinx decodes a first utterance
whole, seconds on a loaded machine): without a word the orchestrator declares the component dead and
it registers again, losing what it had signed (the final CI rehearsal of stop 23). Around such a call
``ControlClient.quiet_for`` says beforehand how long the silence may be, and nothing is declared dead.

The GIL is held here by libc's ``usleep`` called through ctypes.PyDLL (which, unlike CDLL, keeps the
GIL): a wall-clock hold, as long on a loaded machine as on a quiet one."""
from __future__ import annotations

import contextlib
import ctypes
import threading
import time

import pytest

from esiaf import Component
from esiaf.tools.testing import Orchestrator, poll

HOLD_S = 2.0  # more than dead_after_s below, less than it plus the idle interval


class Idle(Component):
    service = "idle"

    def produce(self):
        while not self.stopping:
            self.sleep_until(time.monotonic() + 0.05)


def hold_the_gil(seconds: float) -> None:
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


@pytest.fixture
def running(tmp_path):
    orchestrator = Orchestrator(tmp_path, config={"heartbeat_interval_s": 0.2, "dead_after_s": 0.8,
                                                  "idle_heartbeat_interval_s": 5.0})
    component = Idle(Idle.Settings(name="idle", orchestrator_url=orchestrator.url))
    thread = threading.Thread(target=component.run, daemon=True)
    thread.start()
    try:
        poll(lambda: component.control is not None and component.control.registration
             and orchestrator.component("idle"), timeout_s=30)
        yield orchestrator, component
    finally:
        component.stop()
        thread.join(timeout=10)
        orchestrator.close()


@pytest.mark.parametrize("announced", [True, False], ids=["quiet_for", "unannounced"])
def test_a_component_holding_the_gil_stays_alive_only_if_it_said_so_beforehand(running, announced):
    orchestrator, component = running
    control = component.control
    assert control is not None
    before = control.registration.key_id  # a registration again gets a new key id
    with control.quiet_for(HOLD_S + 1.0) if announced else contextlib.nullcontext():
        held_at = time.monotonic()
        hold_the_gil(HOLD_S)
        assert time.monotonic() - held_at >= HOLD_S * 0.95  # the hold was real
    time.sleep(1.0)  # the heartbeat thread runs again: beats, hears the orchestrator (or that it is unknown)
    if announced:
        assert control.registration.key_id == before, "declared dead and registered again"
        listed = orchestrator.component("idle")
        assert listed is not None and listed["status"] == "alive"
        poll(lambda: orchestrator.component("idle")["heartbeat_interval_s"] == 0.2, timeout_s=3)  # fast again
    else:  # the control case: the same hold, unannounced, is taken for a death
        poll(lambda: control.registration.key_id != before, timeout_s=10)

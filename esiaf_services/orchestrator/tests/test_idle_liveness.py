"""Liveness of components that say they beat slowly while idle, over real DEALER sockets:
one is given dead_after_s plus its idle interval's extra; once it beats fast again, dead_after_s
only, counted from that beat, even though the liveness task was asleep until the slow deadline."""
from __future__ import annotations

import time

import httpx

from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body


def test_slow_then_fast_then_silent_is_dead_after_dead_after_s_not_at_the_slow_deadline(make_orchestrator, zctx):
    orch = make_orchestrator(heartbeat_interval_s=0.2, dead_after_s=0.6, idle_heartbeat_interval_s=4.0)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http:
        vad = FakeComponent(zctx, http, component_body("vad", kind="vad"))
        try:
            vad.heartbeat(interval_s=4.0)  # idle: alive until 0.6 + 3.8 s after this beat
            assert vad.recv() is not None
            time.sleep(1.5)  # past dead_after_s: alive, as it said it beats slowly
            assert [c["heartbeat_interval_s"] for c in http.get("/components").json()["items"]] == [4.0]
            vad.heartbeat(interval_s=0.2)  # audio came: fast again, and then it hangs
            assert vad.recv() is not None
            silent_since = time.monotonic()
            while http.get("/components").json()["items"]:
                assert time.monotonic() - silent_since < 2.0, "not declared dead within dead_after_s of its fast beat"
                time.sleep(0.05)
            assert time.monotonic() - silent_since > 0.5
        finally:
            vad.close()

"""Idle components beat slowly (issue 18): the SDK's heartbeat thread against a fake orchestrator (a
ROUTER in the test), and a real consumer process against the real orchestrator: after an idle interval
with nothing to do its beats say, and keep, the idle interval; the orchestrator gives it that much
longer before it is dead; audio brings the fast interval back at once (docs/protocol.md, "Control")."""
from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zmq

from esiaf import AudioFormat, Component
from esiaf.control import ControlClient, Registration
from esiaf.testing import REPO, Orchestrator, poll
from tests.test_control_ack import fake_orchestrator


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[zmq.Socket, ControlClient, list[Registration]]]:
    """The orchestrator's ROUTER, a started client (fast 0.1 s, idle 0.8 s; the orchestrator is gone
    after 0.35 s of silence) and the registrations it made."""
    with fake_orchestrator(monkeypatch, heartbeat_interval_s=0.1, dead_after_s=0.35,
                           idle_heartbeat_interval_s=0.8) as (router, _, client, made):
        yield router, client, made


def answer_beats(router: zmq.Socket, seconds: float) -> list[tuple[float, dict[str, Any]]]:
    """Acks every heartbeat for ``seconds``; each with when it came."""
    beats = []
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        if router.poll(max(1, int(left * 1000))):
            route, data = router.recv_multipart()
            beats.append((time.monotonic(), json.loads(data)))
            router.send_multipart([route, json.dumps({"type": "ack", "version": 0}).encode()])
    return beats


def test_an_idle_client_beats_at_the_idle_interval_and_busy_brings_the_fast_one_back(fake):
    router, client, made = fake
    beats = answer_beats(router, 0.5)
    assert beats and all(b["interval_s"] == 0.1 for _, b in beats)  # just registered: fast
    beats = answer_beats(router, 3.0)
    slow = [(t, b) for t, b in beats if b["interval_s"] == 0.8]
    assert len(slow) >= 2, [b["interval_s"] for _, b in beats]
    assert all(b1 - b0 > 0.6 for (b0, _), (b1, _) in itertools.pairwise(slow))  # one beat per idle interval
    # beats 0.8 s apart: longer than the orchestrator's 0.35 s of silence, yet not taken for its death
    assert len(made) == 1, "registered again while idle"
    client.busy()  # audio: a beat at once, at the fast interval
    woken_at = time.monotonic()
    (came, first), *rest = answer_beats(router, 0.6)
    assert first["interval_s"] == 0.1 and came - woken_at < 0.2
    assert all(b["interval_s"] == 0.1 for _, b in rest) and len(rest) >= 3


class Source(Component):
    service = "source"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("source/audio", AudioFormat(16000, "int16"))
        self.chunks = 0  # to publish, from its own thread

    def produce(self):
        while not self.stopping:
            while self.chunks:
                self.chunks -= 1
                now = time.time_ns()
                self.publish("source/audio", np.zeros(160, np.int16), now - 10_000_000, now)
            self.sleep_until(time.monotonic() + 0.02)


def test_an_idle_process_beats_slowly_stays_alive_and_beats_fast_again_when_audio_comes(tmp_path):
    orchestrator = Orchestrator(tmp_path, config={"heartbeat_interval_s": 0.2, "dead_after_s": 0.8,
                                                  "idle_heartbeat_interval_s": 2.0})
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    sink = subprocess.Popen([sys.executable, str(REPO / "tests" / "replica_sink.py"), orchestrator.url,
                             str(tmp_path / "sink.txt"), "sink-1"], cwd=REPO, env=env, stderr=subprocess.DEVNULL)
    source = Source(Source.Settings(name="source", orchestrator_url=orchestrator.url))
    thread = threading.Thread(target=source.run, daemon=True)
    try:
        poll(lambda: orchestrator.component("sink"), timeout_s=30)
        assert orchestrator.component("sink")["heartbeat_interval_s"] == 0.2  # just registered: fast
        poll(lambda: orchestrator.component("sink")["heartbeat_interval_s"] == 2.0, timeout_s=10)
        # silent for 2 s at a time, longer than dead_after_s: alive all along, as it said it would be
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            listed = orchestrator.component("sink")
            assert listed is not None and listed["status"] == "alive"
            time.sleep(0.2)
        thread.start()
        poll(lambda: source.output_stats["source/audio"].subscribers >= 1, timeout_s=10)
        source.chunks = 5
        audio_at = time.monotonic()
        poll(lambda: orchestrator.component("sink")["heartbeat_interval_s"] == 0.2, timeout_s=3, interval_s=0.02)
        assert time.monotonic() - audio_at < 1.0  # at once, not at its next slow beat
    finally:
        source.stop()
        if thread.is_alive():
            thread.join(timeout=10)
        sink.terminate()
        sink.wait(timeout=10)
        orchestrator.close()

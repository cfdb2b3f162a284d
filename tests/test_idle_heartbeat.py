"""Idle components beat slowly: the SDK's heartbeat thread against a fake orchestrator (a
ROUTER in the test), and a real consumer process against the real orchestrator: after an idle interval
with nothing to do its beats say, and keep, the idle interval; the orchestrator gives it that much
longer before it is dead; audio brings the fast interval back at once (docs/protocol.md, "Control")."""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import selectors
import socket
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
from esiaf.tools.testing import REPO, Orchestrator, free_port, poll
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
        # registered, and its first beat heard (until then the interval is not known: None)
        poll(lambda: (orchestrator.component("sink") or {}).get("heartbeat_interval_s") is not None, timeout_s=30)
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


def sink_process(orchestrator: Orchestrator, tmp_path, instance: str = "sink-1") -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, str(REPO / "tests" / "replica_sink.py"), orchestrator.url,
                             str(tmp_path / f"{instance}.txt"), instance], cwd=REPO, env=env,
                            stderr=subprocess.DEVNULL)


def test_a_killed_process_is_dead_at_once_through_its_closed_connection_not_after_dead_after_s(tmp_path):
    orchestrator = Orchestrator(tmp_path, config={"dead_after_s": 20.0, "disconnect_grace_s": 0.5})
    sink = sink_process(orchestrator, tmp_path)
    try:
        poll(lambda: orchestrator.component("sink"), timeout_s=30)
        time.sleep(0.5)
        sink.kill()  # SIGKILL: no unregistration, no word; its kernel closes its connections
        sink.wait()
        killed_at = time.monotonic()
        poll(lambda: orchestrator.component("sink") is None, timeout_s=10)
        assert time.monotonic() - killed_at < 3.0  # the grace period (0.5 s) and a loaded machine; not 20 s
        assert "reported=disconnected" in (tmp_path / "orchestrator.log").read_text()
    finally:
        if sink.poll() is None:
            sink.kill()
            sink.wait()
        orchestrator.close()


class CuttableProxy:
    """TCP forwarders from 127.0.0.2:PORT to 127.0.0.1:PORT, in a thread; cut() closes every
    connection under way (both ends see it close), as a network fault would; new ones are forwarded."""

    def __init__(self, ports: list[int]) -> None:
        self.selector = selectors.DefaultSelector()
        self.pairs: dict[socket.socket, socket.socket] = {}
        self.accepted = 0
        self._lock = threading.Lock()
        self._stop = False
        for port in ports:
            listener = socket.create_server(("127.0.0.2", port))
            listener.setblocking(False)
            self.selector.register(listener, selectors.EVENT_READ, port)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop:
            for key, _ in self.selector.select(timeout=0.05):
                with self._lock:
                    if isinstance(key.data, int):  # a listener
                        client, _ = key.fileobj.accept()  # type: ignore[union-attr]
                        upstream = socket.create_connection(("127.0.0.1", key.data))
                        self.accepted += 1
                        for a, b in ((client, upstream), (upstream, client)):
                            self.pairs[a] = b
                            self.selector.register(a, selectors.EVENT_READ, None)
                    elif key.fileobj in self.pairs:
                        conn = key.fileobj
                        assert isinstance(conn, socket.socket)
                        try:
                            data = conn.recv(65536)
                            if data:
                                self.pairs[conn].sendall(data)
                                continue
                        except OSError:
                            pass
                        self._close(conn)

    def _close(self, conn: socket.socket) -> None:
        other = self.pairs.pop(conn, None)
        for s in (conn, other):
            if s is not None:
                self.pairs.pop(s, None)
                with contextlib.suppress(KeyError, ValueError):
                    self.selector.unregister(s)
                s.close()

    def cut(self) -> int:
        with self._lock:
            cut = len(self.pairs) // 2
            for conn in list(self.pairs):
                self._close(conn)
        return cut

    def close(self) -> None:
        self._stop = True
        self.thread.join(timeout=5)
        self.cut()
        for key in list(self.selector.get_map().values()):
            key.fileobj.close()  # type: ignore[union-attr]


def test_a_connection_made_again_does_not_kill_a_live_idle_component(tmp_path):
    control_port, results_port = free_port(), free_port()
    orchestrator = Orchestrator(tmp_path, config={
        "heartbeat_interval_s": 0.2, "dead_after_s": 1.0, "idle_heartbeat_interval_s": 3.0, "disconnect_grace_s": 0.5,
        "advertise_host": "127.0.0.2"}, env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": str(control_port),
                                             "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(results_port)})
    proxy = CuttableProxy([control_port, results_port])
    sink = sink_process(orchestrator, tmp_path)
    try:
        poll(lambda: orchestrator.component("sink"), timeout_s=30)
        registered = poll(lambda: (c := orchestrator.component("sink")) and c["heartbeat_interval_s"] == 3.0 and c,
                          timeout_s=10)
        assert proxy.cut() >= 1  # its control connection (and its results connection) closed
        cut_at = time.monotonic()
        poll(lambda: proxy.accepted >= 4, timeout_s=5)  # libzmq connected again
        while time.monotonic() - cut_at < 4.0:  # past the grace period, and the next idle beat's time
            listed = orchestrator.component("sink")
            assert listed is not None and listed["registered_ns"] == registered["registered_ns"], \
                "declared dead (and registered again) after its connection was made again"
            time.sleep(0.2)
        assert "reported=disconnected" not in (tmp_path / "orchestrator.log").read_text()
    finally:
        sink.terminate()
        sink.wait(timeout=10)
        proxy.close()
        orchestrator.close()

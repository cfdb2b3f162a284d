"""Test helpers: the real app under uvicorn on a random loopback port, and fake components
made of real ZeroMQ sockets. Everything waits on events or polls with a deadline."""
from __future__ import annotations

import asyncio
import itertools
import json
import socket
import threading
import time
from collections.abc import Callable, Sequence
from types import SimpleNamespace
from typing import Any

import httpx
import uvicorn
import zmq

from esiaf.binding import signed
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import make_result
from esiaf_services.orchestrator.api.app import create_app
from esiaf_services.orchestrator.settings import OrchestratorSettings

START_TIMEOUT_S = 10.0
FMT16 = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


def wait_until(predicate: Callable[[], Any], timeout_s: float = 5.0, what: str = "condition",
               interval_s: float = 0.01) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        threading.Event().wait(interval_s)  # poll interval, bounded by the deadline


class RunningOrchestrator:
    """create_app(settings) served by uvicorn in a background thread with its own loop."""

    def __init__(self, settings: OrchestratorSettings) -> None:
        self.settings = settings
        self.app = create_app(settings)
        self._sock = socket.socket()
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(128)
        self.port = self._sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.ws_url = f"ws://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(self.app, log_config=None, lifespan="on",
                                                    timeout_graceful_shutdown=2))
        self._thread = threading.Thread(
            target=lambda: asyncio.run(self.server.serve(sockets=[self._sock])), daemon=True)

    def start(self) -> RunningOrchestrator:
        self._thread.start()
        wait_until(lambda: self.server.started or not self._thread.is_alive(), START_TIMEOUT_S,
                   "the orchestrator to start")
        assert self.server.started, "the orchestrator did not start (see the log)"
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self._thread.join(START_TIMEOUT_S)
        self._sock.close()

    @property
    def core(self):
        return self.app.state.core


_ports = itertools.count(41000)  # fake audio endpoints: nothing connects to them


def component_body(name: str, kind: str = "other", inputs: Sequence[str] = (),
                   outputs: Sequence[str] = (), fmt: dict = FMT16, endpoint: str | None = None,
                   **extra: Any) -> dict:
    return {"name": name, "kind": kind,
            "inputs": [{"topic": t, "format": fmt} for t in inputs],
            "outputs": [{"topic": t, "format": fmt} for t in outputs],
            "audio_endpoint": endpoint or (f"tcp://127.0.0.1:{next(_ports)}" if outputs else None),
            "host": "test", "pid": 1, **extra}


class FakeComponent:
    """Registers over HTTP, then talks over a real DEALER (control) and PUSH (results)."""

    def __init__(self, ctx: zmq.Context, http: httpx.Client, body: dict) -> None:
        response = http.post("/components", json=body)
        assert response.status_code == 201, response.text
        self.registration = response.json()
        self.id = self.registration["component_id"]
        self.name = body["name"]
        self.dealer = ctx.socket(zmq.DEALER)
        self.dealer.setsockopt(zmq.LINGER, 0)  # no IDENTITY, as the SDK: the heartbeat names it
        self.dealer.connect(self.registration["control_endpoint"])
        self.push = ctx.socket(zmq.PUSH)
        self.push.setsockopt(zmq.LINGER, 0)
        self.push.connect(self.registration["results_endpoint"])
        self.sequence = 0

    def heartbeat(self, stats: dict | None = None, **extra: Any) -> None:
        """``extra``: more fields, e.g. ``state_version`` (without it, every answer is the full state)."""
        self.dealer.send_json({"type": "heartbeat", "component_id": self.id,
                               "control_key": self.registration["control_key"],
                               "stats": stats or {"inputs": {}, "outputs": {},
                                                  "results_sent": self.sequence, "info": {}}, **extra})

    def recv(self, timeout_s: float = 5.0) -> dict | None:
        if self.dealer.poll(int(timeout_s * 1000)):
            return self.dealer.recv_json()
        return None

    def wait_for(self, predicate: Callable[[dict], bool], timeout_s: float = 5.0,
                 heartbeat_every_s: float | None = None) -> dict:
        """The first control message that satisfies ``predicate``; heartbeats meanwhile if asked."""
        deadline = time.monotonic() + timeout_s
        next_heartbeat = time.monotonic()
        while (now := time.monotonic()) < deadline:
            if heartbeat_every_s is not None and now >= next_heartbeat:
                self.heartbeat()
                next_heartbeat = now + heartbeat_every_s
            wait_s = min(deadline, next_heartbeat if heartbeat_every_s else deadline) - now
            message = self.recv(max(wait_s, 0.001))
            if message is not None and predicate(message):
                return message
        raise AssertionError(f"{self.name}: no matching control message within {timeout_s} s")

    def keep_alive(self, duration_s: float, every_s: float = 0.5) -> list[dict]:
        """Heartbeats like a real component for ``duration_s``; returns the answers."""
        answers = []
        deadline = time.monotonic() + duration_s
        while (now := time.monotonic()) < deadline:
            self.heartbeat()
            next_beat = now + every_s
            while (left := min(next_beat, deadline) - time.monotonic()) > 0:
                message = self.recv(left)
                if message is not None:
                    answers.append(message)
        return answers

    def send_result(self, stream_id: str = "default", start_ns: int = 1_000_000_000,
                    end_ns: int = 2_000_000_000, text: str = "go forward",
                    type_: pb.ResultType = pb.RESULT_TYPE_SPEECH) -> pb.Result:
        self.sequence += 1
        result = pb.Result(component=self.name, type=type_, stream_id=stream_id,
                           produced_ns=time.time_ns(), sequence=self.sequence, instance=self.id)
        result.span.start_ns, result.span.end_ns = start_ns, end_ns
        if type_ == pb.RESULT_TYPE_SPEECH:
            hypothesis = result.speech.hypotheses.add(text=text, probability=0.93)
            hypothesis.words.add(word=text.split()[0], start_ns=start_ns,
                                 end_ns=start_ns + 100_000_000, probability=0.99)
        elif type_ == pb.RESULT_TYPE_VAD:
            result.vad.probability = 0.8
        self.send(b"result", result.SerializeToString())
        return result

    def emit(self, type_name: str, span: tuple[int, int], stream_id: str = "default",
             **payload: Any) -> pb.Result:
        """Sends one result of any type (payload as for esiaf.results.make_result)."""
        self.sequence += 1
        result = make_result(self.name, type_name, stream_id, span, self.sequence, **payload)
        result.instance = self.id
        self.send(b"result", result.SerializeToString())
        return result

    def end_of_stream(self, stream_id: str = "default") -> None:
        self.send(b"end_of_stream", json.dumps(
            {"component_id": self.id, "component": self.name, "stream_id": stream_id}).encode())

    def send(self, kind: bytes, body: bytes) -> None:
        """On the results plane, as the SDK sends it: with this registration's key id and MAC."""
        self.push.send_multipart(signed(kind, body, self.keys))

    @property
    def keys(self) -> SimpleNamespace:
        return SimpleNamespace(key_id=self.registration["key_id"], control_key=self.registration["control_key"])

    def close(self) -> None:
        self.dealer.close(linger=0)
        self.push.close(linger=0)


class Heartbeater:
    """Heartbeats some fake components from a thread of its own (which then owns their
    DEALER sockets) until stopped, so that they stay alive while a test waits."""

    def __init__(self, components: list[FakeComponent], every_s: float = 0.2) -> None:
        self._components = components
        self._every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._every_s):
            for component in self._components:
                component.heartbeat()
                while component.recv(0) is not None:
                    pass

    def drop(self, component: FakeComponent) -> None:
        """Stops beating for ``component``: it falls silent, as if killed."""
        self._components.remove(component)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

"""Fusion overhead and ingest rate of the orchestrator process, at 1 and at 100 concurrent streams.

Each stream has its own ASR, SSL and emotion components (registered over HTTP); one fusion
``utterance`` anchors on speech and fuses ssl and emotion. Per utterance (2 s of capture time) a
stream sends 16 SSL results of 125 ms, the anchor, then the emotion result, which is the last
result the fusion needs: it completes the fusion.

- overhead (in the orchestrator): the completing result's reception → its fused result handed
  to the websocket clients; the orchestrator measures it (``GET /fusions/stats``);
- end to end (upper bound, includes ZeroMQ and websocket hops and this process's own GIL):
  just before the completing result is sent → its fused result received on the websocket;
- timer lateness: fusions whose emotion component never answers (timeout 0.2 s): deadline →
  fused result handed to the websocket clients (a timer wakes at the deadline; nothing polls);
- ingest rate: results sent as fast as one PUSH socket can, until the orchestrator has stored
  them all (committed in SQLite, fused where they complete something).

    python bench/fusion.py [--streams 1,100] [--utterances 300] [--ingest 20000]

Prints ``name=value`` lines.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import zmq
from websockets.sync.client import connect

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.results import make_result, ssl_direction  # noqa: E402
from esiaf.tools.testing import Orchestrator, poll, signed_result  # noqa: E402
from esiaf_services.orchestrator.fusion.latency import percentile  # noqa: E402

S = 1_000_000_000
UTTERANCE_NS = 2 * S
CHUNKS = 16
CONFIG = {"heartbeat_interval_s": 600.0, "idle_heartbeat_interval_s": 600.0, "dead_after_s": 3600.0,
          "timeouts": {"initial_s": 30.0},
          "log_level": "WARNING",
          "fusions": [{"name": "utterance", "anchor": "speech", "fuse": ["ssl", "emotion"]}]}
FMT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


def register(orchestrator: Orchestrator, streams: int) -> tuple[str, dict[str, dict]]:
    """The results endpoint, and each component's registration (its results are signed with it): one
    recogniser, one ssl and one emotion service hearing every stream, as a deployment's services do
    (fusion waits for every live service of a fused type on every stream)."""
    endpoint, registrations = "", {}
    for name, kind in (("asr", "speech"), ("ssl", "ssl"), ("emotion", "emotion")):
        response = orchestrator.http.post("/components", json={
            "name": name, "kind": kind,
            "inputs": [{"topic": f"in/{i}", "format": FMT} for i in range(streams)]})
        response.raise_for_status()
        registrations[name] = response.json()
        endpoint = response.json()["results_endpoint"]
    return endpoint, registrations


class Receiver(threading.Thread):
    """Collects the arrival time of every fused result, by (stream, anchor start)."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self._open = ExitStack()  # entered as websockets asks (a bare connect() is deprecated)
        self.ws = self._open.enter_context(connect(url, max_size=None))
        self.arrived: dict[tuple[str, int], int] = {}
        self.done = threading.Event()

    def run(self) -> None:
        try:
            for text in self.ws:
                now = time.time_ns()
                fused = json.loads(text)
                if fused.get("type") == "fused_result" and fused["revision"] == 1:
                    self.arrived[(fused["stream_id"], fused["anchor"]["span"]["start_ns"])] = now
        except Exception:  # closed at the end
            pass
        self.done.set()


def overhead_run(streams: int, utterances: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        orchestrator = Orchestrator(Path(tmp), CONFIG)
        try:
            endpoint, registrations = register(orchestrator, streams)
            ctx = zmq.Context()
            push = ctx.socket(zmq.PUSH)
            push.setsockopt(zmq.LINGER, 0)
            push.connect(endpoint)
            receiver = Receiver(f"{orchestrator.ws_url}/ws/fused")
            receiver.start()
            sent: dict[tuple[str, int], int] = {}
            sequence = 0
            rounds = max(1, utterances // streams)
            # one utterance per stream per round; streams spread evenly over the round
            round_s = UTTERANCE_NS / S if streams > 1 else 0.02
            start = time.monotonic()
            base = time.time_ns() - UTTERANCE_NS  # capture time: consecutive utterances
            for r in range(rounds):
                for i in range(streams):
                    due = start + (r + i / streams) * round_s
                    while (left := due - time.monotonic()) > 0:
                        time.sleep(left)
                    stream = f"s{i}"
                    begin = base + r * UTTERANCE_NS
                    end = begin + UTTERANCE_NS
                    chunk = UTTERANCE_NS // CHUNKS
                    for c in range(CHUNKS):
                        sequence += 1
                        push.send_multipart(signed_result(registrations["ssl"], make_result(
                            "ssl", "ssl", stream, (begin + c * chunk, begin + (c + 1) * chunk),
                            sequence, ssl={"directions": [ssl_direction(30.0 * c)]})))
                    push.send_multipart(signed_result(registrations["asr"], make_result(
                        "asr", "speech", stream, (begin, end), sequence,
                        speech={"hypotheses": [{"text": "hello", "probability": 0.9}]})))
                    last = signed_result(registrations["emotion"], make_result(
                        "emotion", "emotion", stream, (begin, end), sequence,
                        emotion={"label": "happy", "probability": 0.8}))
                    sent[(stream, begin)] = time.time_ns()
                    push.send_multipart(last)
            poll(lambda: len(receiver.arrived) >= len(sent), timeout_s=60)
            stats = orchestrator.http.get("/fusions/stats").json()
            receiver._open.close()
            push.close(linger=0)
            ctx.term()
        finally:
            orchestrator.close()
    e2e_ms = [(receiver.arrived[key] - t) / 1e6 for key, t in sent.items()]
    return {"fusions": len(sent), "overhead_p50_ms": stats["overhead_p50_ms"],
            "overhead_p99_ms": stats["overhead_p99_ms"],
            "e2e_p50_ms": percentile(e2e_ms, 0.5), "e2e_p99_ms": percentile(e2e_ms, 0.99),
            "complete": stats["counters"].get("completion_complete", 0)}


def timeout_run(fusions: int) -> dict[str, float]:
    """Fusions whose emotion component never answers: how late after its deadline (window end
    + timeout) each is handed to the websocket clients."""
    with tempfile.TemporaryDirectory() as tmp:
        orchestrator = Orchestrator(Path(tmp), {**CONFIG, "timeouts": {"initial_s": 0.2}})
        try:
            endpoint, registrations = register(orchestrator, 1)
            ctx = zmq.Context()
            push = ctx.socket(zmq.PUSH)
            push.setsockopt(zmq.LINGER, 0)
            push.connect(endpoint)
            window_ns = 20_000_000  # windows 20 ms apart never overlap: no revisions
            for n in range(fusions):
                end = time.time_ns()
                for name, type_name, payload in (
                        ("ssl", "ssl", {"ssl": {"directions": [ssl_direction(90.0)]}}),
                        ("asr", "speech", {"speech": {"hypotheses": []}})):
                    push.send_multipart(signed_result(registrations[name], make_result(
                        name, type_name, "s0", (end - window_ns, end), n + 1, **payload)))
                time.sleep(window_ns / 1e9)
            stats = poll(lambda: (s := orchestrator.http.get("/fusions/stats").json())
                         ["timed_out_samples"] >= fusions and s, timeout_s=30)
            push.close(linger=0)
            ctx.term()
        finally:
            orchestrator.close()
    return {"fusions": fusions, "timer_lateness_p50_ms": stats["timer_lateness_p50_ms"],
            "timer_lateness_p99_ms": stats["timer_lateness_p99_ms"]}


def ingest_run(count: int, streams: int = 100) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        orchestrator = Orchestrator(Path(tmp), CONFIG)
        try:
            endpoint, registrations = register(orchestrator, streams)
            ctx = zmq.Context()
            push = ctx.socket(zmq.PUSH)
            push.setsockopt(zmq.LINGER, 0)
            push.setsockopt(zmq.SNDHWM, count + 1)
            push.connect(endpoint)
            base = time.time_ns() - 3600 * S
            chunk = UTTERANCE_NS // CHUNKS
            messages = [signed_result(registrations["ssl"], make_result(
                "ssl", "ssl", f"s{n % streams}",
                (base + (n // streams) * chunk, base + (n // streams + 1) * chunk),
                n + 1, ssl={"directions": [ssl_direction(float(n % 360))]})) for n in range(count)]
            started = time.monotonic()
            for message in messages:
                push.send_multipart(message)
            poll(lambda: orchestrator.http.get("/fusions/stats").json()["counters"].get("results", 0)
                 >= count, timeout_s=120, interval_s=0.01)
            elapsed = time.monotonic() - started
            push.close(linger=0)
            ctx.term()
        finally:
            orchestrator.close()
    return {"results": count, "seconds": elapsed, "results_per_s": count / elapsed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--streams", default="1,100", help="comma-separated stream counts")
    parser.add_argument("--utterances", type=int, default=300, help="fusions per stream count")
    parser.add_argument("--ingest", type=int, default=20000, help="results for the ingest rate")
    args = parser.parse_args()
    for streams in (int(s) for s in args.streams.split(",")):
        figures = overhead_run(streams, args.utterances)
        for name, value in figures.items():
            print(f"streams_{streams}_{name}={value:.3f}" if isinstance(value, float)
                  else f"streams_{streams}_{name}={value}", flush=True)
    for name, value in timeout_run(100).items():
        print(f"timed_out_{name}={value:.3f}" if isinstance(value, float)
              else f"timed_out_{name}={value}", flush=True)
    if args.ingest:
        for name, value in ingest_run(args.ingest).items():
            print(f"ingest_{name}={value:.1f}", flush=True)


if __name__ == "__main__":
    main()

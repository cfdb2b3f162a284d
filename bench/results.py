"""The orchestrator's CPU per result: received, stored, fused and sent to a websocket client.

    python -m bench.results [--results 1000] [--repeats 3] [--against DIR] [--profile FILE] [--port 27700]

A real orchestrator (its own process; ``--against DIR``: another checkout's, run interleaved with
this one's), a registered asr (no heartbeats: its registration's key signs the results), and a
websocket client following fused results as ``esiaf run`` does. The asr sends ``--results``
speech results, one every 20 ms (so each is its own batch, as in a live pipeline), each anchoring a
fused result (the default fusion waits for nobody live); the orchestrator's CPU over that phase,
the final checkpoint included, is divided by the results stored.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import psutil
import zmq
from websockets.sync.client import connect

from bench.heartbeat import orchestrator_process
from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.testing import poll, signed_result

REPO = Path(__file__).resolve().parent.parent
FORMAT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


def one_run(repo: Path, port: int, count: int, profile: Path | None = None) -> dict[str, float]:
    orchestrator, url, _ = orchestrator_process(repo, port, "esiaf-results-")
    context = zmq.Context()
    try:
        poll(lambda: httpx.get(f"{url}/health").status_code == 200, timeout_s=30)
        registration = httpx.post(f"{url}/components", json={
            "name": "asr", "kind": "speech", "stream_id": "robot",
            "inputs": [{"topic": "audio/vad", "format": FORMAT}], "outputs": [], "host": "bench", "info": {}}).json()
        push = context.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(registration["results_endpoint"])
        fused = []
        with connect(f"ws://127.0.0.1:{port}/ws/fused?stream=robot") as ws:
            def follow() -> None:
                for text in ws:
                    fused.append(json.loads(text).get("type"))
            threading.Thread(target=follow, daemon=True).start()
            handle = psutil.Process(orchestrator.pid)
            spy = None if profile is None else subprocess.Popen(  # py-spy --gil: what holds the interpreter
                [str(Path(sys.executable).with_name("py-spy")), "record", "--pid", str(orchestrator.pid), "--rate",
                 "500", "--gil", "--nonblocking", "--format", "raw", "-o", str(profile)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.0)
            before = sum(handle.cpu_times()[:2])
            start_ns = time.time_ns()
            for number in range(count):
                result = pb.Result(component="asr", type=pb.RESULT_TYPE_SPEECH, stream_id="robot",
                                   produced_ns=time.time_ns(), sequence=number)
                result.span.start_ns = start_ns + number * 10**9
                result.span.end_ns = result.span.start_ns + 5 * 10**8
                result.speech.hypotheses.add(text="where is the kitchen", probability=0.9)
                push.send_multipart(signed_result(registration, result))
                time.sleep(0.02)
            poll(lambda: fused.count("fused_result") >= count, timeout_s=30)
            time.sleep(1.5)  # the checkpoint after the last write
            cpu_s = sum(handle.cpu_times()[:2]) - before
            if spy is not None:
                spy.send_signal(2)  # SIGINT: it writes what it has
                spy.wait(timeout=30)
    finally:
        context.destroy(linger=0)
        orchestrator.terminate()
        orchestrator.wait(timeout=10)
    return {"orchestrator_us": cpu_s * 1e6 / count}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--results", type=int, default=1000, help="results per run (1000)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per checkout, interleaved (3)")
    parser.add_argument("--against", type=Path, metavar="DIR", help="another checkout, run interleaved")
    parser.add_argument("--port", type=int, default=27700, help="first HTTP port; the next two its control and "
                        "results ports; each run the next 3")
    parser.add_argument("--profile", type=Path, metavar="FILE", help="py-spy the orchestrator (one run) and "
                        "print its top functions")
    args = parser.parse_args()
    if args.profile is not None:
        print(one_run(REPO, args.port, args.results, args.profile))
        from bench.framework import top_functions
        print(*top_functions(args.profile, 40), sep="\n")
        return
    codes = {"this": REPO, **({"against": args.against.resolve()} if args.against else {})}
    runs: dict[str, list[float]] = {code: [] for code in codes}
    port = args.port
    for repeat in range(args.repeats):
        for code, repo in codes.items():
            runs[code].append(one_run(repo, port, args.results)["orchestrator_us"])
            port += 3
            print(f"repeat {repeat + 1} {code}: {runs[code][-1]:.0f} us per result", file=sys.stderr, flush=True)
    print(f"{args.results} results a run, {args.repeats} repeats; the orchestrator's CPU-us per result (median; runs)")
    for code, values in runs.items():
        print(f"{code}: {statistics.median(values):.0f} ({', '.join(f'{v:.0f}' for v in values)})")
    with open("/proc/loadavg") as handle:
        print("load average:", " ".join(handle.read().split()[:3]))


if __name__ == "__main__":
    main()

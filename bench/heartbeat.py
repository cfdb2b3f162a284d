"""The cost of one heartbeat: the orchestrator's CPU, and the component side's, per beat.

    python -m bench.heartbeat [--beats 3000] [--components 3] [--repeats 3] [--against DIR]
                              [--profile DIR] [--port 27300]

Starts a real orchestrator (its own process) and, in another process, ``--components`` real
``esiaf.control.ControlClient`` s registered like a vad (an input, an output, stats like its
heartbeats'); each is poked ``--beats`` times (a heartbeat each, answered by the orchestrator,
about 400 a second in all), and both processes' CPU time over that phase is divided by the beats
the orchestrator counted. ``--against DIR`` runs another checkout's code (both processes)
interleaved with this one's; ``--profile DIR`` samples the orchestrator with py-spy instead (one
run, its top functions printed). The framework's busy heartbeats are 2 a second per component
(``heartbeat_interval_s`` 0.5 s): 7,200 an hour each, so 100 us a beat is 0.72 CPU-s per hour of
audio per component.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[1] == "--clients":
    sys.path[0] = sys.argv[2]  # the client side runs the checkout under test's esiaf

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time

REPO = Path(__file__).resolve().parent.parent
FORMAT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


def clients(url: str, components: int, beats: int) -> None:
    """The component side: registers, waits for "go" on stdin, pokes, prints its CPU time."""
    import zmq

    from esiaf.control import ControlClient
    counts = {"published": 0}

    def stats() -> dict:  # like a vad's (esiaf.node.Context.stats)
        counts["published"] += 1
        return {"inputs": {"audio/raw": {"received": counts["published"] * 5, "lost": 0, "bad": 0, "queued": 0}},
                "outputs": {"vad": {"published": counts["published"], "dropped": 0, "subscribers": 1}},
                "results_sent": 12, "results_dropped": 0, "refused": {}, "refused_by_publisher": {},
                "refused_subscribers": {}, "info": {"backend": "silero", "segments": 12}}

    context = zmq.Context()
    running = []
    for number in range(components):
        request = {"name": f"vad{number}", "kind": "vad", "stream_id": "robot",
                   "inputs": [{"topic": "audio/raw", "format": FORMAT}],
                   "outputs": [{"topic": f"vad{number}", "format": FORMAT}],
                   "audio_endpoint": f"tcp://127.0.0.1:{27900 + number}", "host": "bench", "info": {}}
        client = ControlClient(context, url, request, stats, register_timeout_s=30)
        client.start()
        running.append(client)
    time.sleep(1.0)  # the first beats and their full states
    print("ready", flush=True)
    sys.stdin.readline()
    import psutil
    beating = {client._thread.native_id for client in running if client._thread is not None}

    def beating_cpu_s() -> float:  # the heartbeat threads' alone (not this one's pokes)
        return sum(t.user_time + t.system_time for t in psutil.Process().threads() if t.id in beating)
    started, started_beating = time.process_time(), beating_cpu_s()
    for _ in range(beats):
        for client in running:  # one at a time, as the framework's beats come
            client.poke()
            time.sleep(1 / 400)
    time.sleep(0.2)  # the last answers
    print(json.dumps({"cpu_s": time.process_time() - started, "beating_cpu_s": beating_cpu_s() - started_beating}),
          flush=True)
    for client in running:
        client.stop(unregister_too=False)
    context.term()


def orchestrator_process(repo: Path, port: int, prefix: str) -> tuple[subprocess.Popen, str, dict[str, str]]:
    """A real orchestrator of ``repo``'s code on ``port`` (control and results on the next two), with a
    fresh database; returns the process, its URL and the environment it runs in."""
    workdir = Path(tempfile.mkdtemp(prefix=prefix))
    env = {**os.environ, "PYTHONPATH": str(repo), "ESIAF_ORCHESTRATOR_CONTROL_PORT": str(port + 1),
           "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(port + 2), "ESIAF_ORCHESTRATOR_LOG_LEVEL": "WARNING"}
    orchestrator = subprocess.Popen([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(port),
                                     "--db", str(workdir / "o.db")], cwd=repo, env=env,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return orchestrator, f"http://127.0.0.1:{port}", env


def one_run(repo: Path, port: int, components: int, beats: int, profile: Path | None = None,
            perf: Path | None = None) -> dict[str, float]:
    import httpx
    import psutil
    orchestrator, url, env = orchestrator_process(repo, port, "esiaf-heartbeat-")
    client = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--clients", str(repo), url,
                               str(components), str(beats)], cwd=repo, env=env, stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    spies: list[subprocess.Popen] = []
    try:
        assert client.stdout is not None and client.stdin is not None
        if client.stdout.readline().strip() != "ready":
            raise SystemExit("bench/heartbeat.py: the clients did not start")

        def heartbeats() -> int:
            return sum(c["heartbeats"] for c in httpx.get(f"{url}/components").json()["items"])
        handle = psutil.Process(orchestrator.pid)
        if profile is not None:  # --gil: only what holds the interpreter (py-spy counts a woken, runnable
            for name, pid in (("orchestrator", orchestrator.pid), ("component", client.pid)):  # thread as busy)
                spies.append(subprocess.Popen([str(Path(sys.executable).with_name("py-spy")), "record", "--pid",
                                               str(pid), "--rate", "500", "--gil", "--nonblocking", "--format",
                                               "raw", "-o", str(profile / f"{name}-heartbeats.txt")],
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        if perf is not None:  # native: the kernel's, libzmq's and the interpreter's shares
            spies.append(subprocess.Popen(["perf", "record", "-F", "2000", "-g", "-o", str(perf),
                                           "-p", str(orchestrator.pid)],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        if spies:
            time.sleep(1.0)
        beats_before, cpu_before, threads_before = heartbeats(), sum(handle.cpu_times()[:2]), thread_cpu_s(handle)
        client.stdin.write("go\n")
        client.stdin.flush()
        client_cpu = json.loads(client.stdout.readline())
        cpu_s, beats_done = sum(handle.cpu_times()[:2]) - cpu_before, heartbeats() - beats_before
        threads = {name: used - threads_before.get(name, 0.0) for name, used in thread_cpu_s(handle).items()}
        client.wait(timeout=30)
    finally:
        for spy in spies:
            spy.send_signal(2)  # SIGINT: the sampler writes what it has
            spy.wait(timeout=30)
        for process in (client, orchestrator):
            if process.poll() is None:
                process.terminate()
                process.wait(timeout=10)
    return {"beats": beats_done, "orchestrator_us": cpu_s * 1e6 / beats_done,
            "component_us": client_cpu["cpu_s"] * 1e6 / beats_done,
            "component_heartbeat_thread_us": client_cpu["beating_cpu_s"] * 1e6 / beats_done,
            **{f"orchestrator_{name}_us": used * 1e6 / beats_done for name, used in threads.items() if used > 0}}


def thread_cpu_s(process) -> dict[str, float]:  # type: ignore[no-untyped-def]
    """CPU seconds of each of its threads, by name (libzmq's I/O thread is "ZMQbg/IO/0")."""
    used: dict[str, float] = {}
    for thread in process.threads():
        try:
            name = Path(f"/proc/{process.pid}/task/{thread.id}/comm").read_text().strip()
        except OSError:
            continue
        used[name] = used.get(name, 0.0) + thread.user_time + thread.system_time
    return used


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--beats", type=int, default=3000, help="heartbeats per component per run (3000)")
    parser.add_argument("--components", type=int, default=3, help="components beating (3)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per checkout, interleaved (3)")
    parser.add_argument("--against", type=Path, metavar="DIR", help="another checkout, run interleaved")
    parser.add_argument("--profile", type=Path, metavar="DIR", help="py-spy the orchestrator (one run)")
    parser.add_argument("--perf", type=Path, metavar="FILE", help="perf record the orchestrator (one run)")
    parser.add_argument("--port", type=int, default=27300, help="first HTTP port; +1, +2 control and results; "
                        "each run the next 3")
    args = parser.parse_args()
    if args.profile is not None:
        args.profile.mkdir(parents=True, exist_ok=True)
        print(one_run(REPO, args.port, args.components, args.beats, args.profile))
        from bench.framework import top_functions
        for name in ("orchestrator", "component"):
            print(f"== {name}:", *top_functions(args.profile / f"{name}-heartbeats.txt", 30), sep="\n")
        return
    if args.perf is not None:
        print(one_run(REPO, args.port, args.components, args.beats, perf=args.perf))
        return
    codes = {"this": REPO, **({"against": args.against.resolve()} if args.against else {})}
    runs: dict[str, list[dict[str, float]]] = {code: [] for code in codes}
    port = args.port
    for repeat in range(args.repeats):
        for code, repo in codes.items():
            runs[code].append(one_run(repo, port, args.components, args.beats))
            port += 3
            print(f"repeat {repeat + 1} {code}: {runs[code][-1]}", file=sys.stderr, flush=True)
    print(f"{args.components} components x {args.beats} heartbeats, {args.repeats} repeats; CPU-us per heartbeat "
          "(median; the runs)")
    for code, results in runs.items():
        for side in ("orchestrator_us", "orchestrator_python_us", "component_us", "component_heartbeat_thread_us"):
            values = [r[side] for r in results]
            print(f"{code} {side}: {statistics.median(values):.0f} ({', '.join(f'{v:.0f}' for v in values)})")
    with open("/proc/loadavg") as handle:
        print("load average:", " ".join(handle.read().split()[:3]))


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--clients":
        clients(sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
    else:
        main()

"""Half-sent HTTP requests against the orchestrator: what a peer without the token can hold open.

    python -m bench.half_open [--connections 1100] [--open-files 1024] [--hold-s 10] [--port 18601] [--repo DIR]

Starts an orchestrator with a limit of ``--open-files`` open files (soft and hard, as ``ulimit -n``),
opens ``--connections`` connections from 127.0.0.2 that each send ``GET /health HTTP/1.1`` and one
header line and never end their headers, and while they are held asks ``GET /health`` from
127.0.0.1 every 50 ms on a new connection (2 s timeout: a timeout counts as 2 s). Prints
``name=value`` lines: the connections opened and still held at the end, /health's p50, p99 and max
in ms and its failures, the orchestrator's CPU seconds and log bytes from the first connection to
the end of the hold. ``--repo``: the checkout whose orchestrator runs (a worktree of main: the code
before a change).
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import os  # noqa: E402
import socket  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import httpx  # noqa: E402
import psutil  # noqa: E402

from esiaf.tools.testing import file_limit, free_port, half_sent_requests, poll  # noqa: E402

HEALTH_TIMEOUT_S = 2.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connections", type=int, default=1100)
    parser.add_argument("--open-files", type=int, default=1024, help="the orchestrator's limit (soft and hard)")
    parser.add_argument("--hold-s", type=float, default=10.0, help="how long to hold them and time /health")
    parser.add_argument("--port", type=int, default=0, help="the orchestrator's HTTP port (default: any free one)")
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout whose orchestrator runs")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-half-open-"))
    port = args.port or free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(args.repo.resolve()), "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0",
           "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0", "ESIAF_TOKEN": "bench-token"}
    log_path = workdir / "orchestrator.log"
    with log_path.open("wb") as log:
        orchestrator = subprocess.Popen(
            [sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(port), "--db", str(workdir / "o.db")],
            cwd=args.repo, env=env, stdout=log, stderr=subprocess.STDOUT, preexec_fn=file_limit(args.open_files))
    held = []
    try:
        with httpx.Client(timeout=HEALTH_TIMEOUT_S) as client:
            poll(lambda: client.get(f"{url}/health").status_code == 200, timeout_s=30)
            process = psutil.Process(orchestrator.pid)
            log_before, times = log_path.stat().st_size, process.cpu_times()
            cpu_before = times.user + times.system
            opening = time.monotonic()
            held = half_sent_requests("127.0.0.1", port, args.connections)
            started = time.monotonic()
            latencies_ms, failures = [], 0
            while time.monotonic() - started < args.hold_s:
                asked = time.monotonic()
                ok = health_ok(port)
                latencies_ms.append((time.monotonic() - asked) * 1000)
                failures += not ok
                time.sleep(max(0.0, 0.05 - (time.monotonic() - asked)))
            alive = sum(1 for sock in held if _open(sock))
            times = process.cpu_times()
            cpu_s = times.user + times.system - cpu_before
        latencies_ms.sort()
        print(f"connections_opened={len(held)}")
        print(f"opening_s={started - opening:.2f}")
        print(f"connections_still_open={alive}")
        print(f"health_requests={len(latencies_ms)}")
        print(f"health_failures={failures}")
        print(f"health_p50_ms={statistics.median(latencies_ms):.1f}")
        print(f"health_p99_ms={latencies_ms[min(len(latencies_ms) - 1, int(0.99 * len(latencies_ms)))]:.1f}")
        print(f"health_max_ms={latencies_ms[-1]:.1f}")
        print(f"orchestrator_cpu_s={cpu_s:.2f}")
        print(f"log_bytes={log_path.stat().st_size - log_before}")
    finally:
        for sock in held:
            sock.close()
        orchestrator.terminate()
        try:
            orchestrator.wait(timeout=10)
        except subprocess.TimeoutExpired:
            orchestrator.kill()
            orchestrator.wait()


def health_ok(port: int) -> bool:
    """``GET /health`` on a new connection, as a health check makes it (a raw socket: no client's own
    set-up in the time measured); whether it answered 200 within HEALTH_TIMEOUT_S."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=HEALTH_TIMEOUT_S) as sock:
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: esiaf\r\nConnection: close\r\n\r\n")
            return sock.recv(12).startswith(b"HTTP/1.1 200")
    except OSError:
        return False


def _open(sock) -> bool:
    """Whether the server still holds this connection (it has neither closed nor reset it)."""
    sock.setblocking(False)
    try:
        return sock.recv(1, socket.MSG_PEEK) != b""
    except BlockingIOError:
        return True
    except OSError:
        return False


if __name__ == "__main__":
    main()

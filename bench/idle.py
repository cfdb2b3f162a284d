"""Idle CPU: the orchestrator and a few services registered and heartbeating, with no audio.

    python bench/idle.py [--seconds 30] [--services vad,asr,gender] [--port 27200] [--repo DIR]

Prints CPU seconds per minute of each process while idle, as ``name=value`` lines
(``idle_cpu_s_per_min_vad=0.02``). The target: at most 0.03 s per minute per service.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import httpx  # noqa: E402
import psutil  # noqa: E402

from esiaf.tools.testing import free_port, poll  # noqa: E402


def cpu_s(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="how long to measure (default 30)")
    parser.add_argument("--services", default="vad,asr,gender", help="services to start beside the orchestrator "
                        "(each must register without a producer upstream: not the splitter)")
    parser.add_argument("--port", type=int, default=0, help="the orchestrator's HTTP port; the next its control "
                        "and results ports, then each service's audio port (default: any free ones)")
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout whose code runs (default this one: "
                        "e.g. a worktree of main, before a change)")
    args = parser.parse_args()
    if args.seconds <= 0:
        raise SystemExit("bench/idle.py: --seconds must be positive")
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-idle-"))
    port = args.port or free_port()
    url = f"http://127.0.0.1:{port}"
    repo = args.repo.resolve()
    env = {**os.environ, "PYTHONPATH": str(repo), "ESIAF_ORCHESTRATOR_URL": url,
           "ESIAF_ORCHESTRATOR_CONTROL_PORT": str(port + 1 if args.port else 0),
           "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(port + 2 if args.port else 0)}
    names = ["orchestrator", *[s for s in args.services.split(",") if s]]
    processes: dict[str, subprocess.Popen] = {}
    try:
        for name in names:
            extra = ["--port", str(port), "--db", str(workdir / "o.db")] if name == "orchestrator" else []
            if args.port and name != "orchestrator":  # each service's audio port after the orchestrator's
                env[f"ESIAF_{name.upper()}_AUDIO_PORT"] = str(port + 2 + len(processes))
            processes[name] = subprocess.Popen([sys.executable, "-m", f"esiaf_services.{name}", *extra], cwd=repo,
                                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            if name == "orchestrator":
                poll(lambda: httpx.get(f"{url}/health").status_code == 200, timeout_s=60)
        poll(lambda: len(httpx.get(f"{url}/components").json()["items"]) == len(names) - 1, timeout_s=120)
        time.sleep(3.0)  # settle after start-up
        handles = {name: psutil.Process(p.pid) for name, p in processes.items()}
        before = {name: cpu_s(h) for name, h in handles.items()}
        print(f"bench/idle: measuring {', '.join(names)} idle for {args.seconds:g} s", file=sys.stderr)
        time.sleep(args.seconds)
        for name, handle in handles.items():
            per_min = (cpu_s(handle) - before[name]) * 60.0 / args.seconds
            print(f"idle_cpu_s_per_min_{name}={per_min:.3f}")
    finally:
        for process in processes.values():
            process.terminate()
        for process in processes.values():
            process.wait(timeout=10)


if __name__ == "__main__":
    main()

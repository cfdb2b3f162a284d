"""Processes asleep while idle, counted as context switches in /proc. The orchestrator's
event loop's thread, with nothing registered and nothing written, does not wake: not for uvicorn's
tick (its Date header is made when read), a checkpoint task that finds nothing written or a liveness
task with no one to watch; a write is still checkpointed within about a second (the WAL copied into the
database file). An idle component's threads wake for its slow heartbeat and little else."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from esiaf.tools.testing import REPO, Orchestrator, poll


def wakeups(pid: int) -> int:
    """Voluntary context switches of the process's main thread (where the event loop runs): its wake-ups."""
    return wakeups_of(pid, pid)


def test_an_idle_orchestrator_does_not_wake_and_still_checkpoints_a_write(tmp_path):
    orchestrator = Orchestrator(tmp_path)
    try:
        time.sleep(2.0)  # start-up done
        before, started = wakeups(orchestrator.process.pid), time.monotonic()
        time.sleep(6.0)
        per_s = (wakeups(orchestrator.process.pid) - before) / (time.monotonic() - started)
        assert per_s < 0.5, f"{per_s:.2f} wake-ups a second"  # it was 2.5: uvicorn's tick, the other two
        database = tmp_path / "o.db"
        written = database.stat().st_mtime_ns
        assert orchestrator.http.put("/streams/s1", json={"start_ns": time.time_ns(), "source": "test",
                                                          "info": {}}).status_code in (200, 201, 204)
        poll(lambda: database.stat().st_mtime_ns != written, timeout_s=5)  # checkpointed
    finally:
        orchestrator.close()


def all_wakeups(pid: int) -> int:
    return sum(wakeups_of(pid, int(tid.name)) for tid in Path(f"/proc/{pid}/task").iterdir())


def wakeups_of(pid: int, tid: int) -> int:
    try:
        status = Path(f"/proc/{pid}/task/{tid}/status").read_text().splitlines()
    except FileNotFoundError:  # a thread that ended
        return 0
    # voluntary switches only: a thread going back to sleep after a wake-up; being preempted while it
    # runs (nonvoluntary) counts the machine's load, not the process's wake-ups
    return sum(int(line.split()[1]) for line in status if line.startswith("voluntary_ctxt"))


def test_an_idle_component_process_wakes_about_once_per_idle_heartbeat(tmp_path):
    """Its heartbeat (every 5 s once idle) and its answer, the data thread's 5 s poll; no ZMTP
    heartbeats on its two TCP connections (they woke libzmq's I/O thread about 6 times a second)."""
    orchestrator = Orchestrator(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    sink = subprocess.Popen([sys.executable, str(REPO / "tests" / "replica_sink.py"), orchestrator.url,
                             str(tmp_path / "sink.txt"), "sink-1"], cwd=REPO, env=env, stderr=subprocess.DEVNULL)
    try:
        poll(lambda: (c := orchestrator.component("sink")) and c["heartbeat_interval_s"] == 5.0, timeout_s=40)
        before, started = all_wakeups(sink.pid), time.monotonic()
        time.sleep(10.0)
        per_s = (all_wakeups(sink.pid) - before) / (time.monotonic() - started)
        assert per_s < 2.0, f"{per_s:.2f} wake-ups a second"
    finally:
        sink.terminate()
        sink.wait(timeout=10)
        orchestrator.close()

"""The orchestrator asleep while idle (issue 18): its event loop's thread, with nothing registered and
nothing written, wakes only for uvicorn's once-a-second tick; not also for a checkpoint task that
finds nothing written or a liveness task with no one to watch. A write is still checkpointed
within about a second (the WAL copied into the database file)."""
from __future__ import annotations

import time
from pathlib import Path

from esiaf.testing import Orchestrator, poll


def wakeups(pid: int) -> int:
    """Context switches of the process's main thread (where the event loop runs): its wake-ups."""
    status = Path(f"/proc/{pid}/task/{pid}/status").read_text().splitlines()
    return sum(int(line.split()[1]) for line in status if line.startswith(("voluntary_ctxt", "nonvoluntary_ctxt")))


def test_an_idle_orchestrator_wakes_about_once_a_second_and_still_checkpoints_a_write(tmp_path):
    orchestrator = Orchestrator(tmp_path)
    try:
        time.sleep(2.0)  # start-up done
        before, started = wakeups(orchestrator.process.pid), time.monotonic()
        time.sleep(6.0)
        per_s = (wakeups(orchestrator.process.pid) - before) / (time.monotonic() - started)
        assert per_s < 1.6, f"{per_s:.2f} wake-ups a second"  # uvicorn's tick; it was 2.4 with the other two
        database = tmp_path / "o.db"
        written = database.stat().st_mtime_ns
        assert orchestrator.http.put("/streams/s1", json={"start_ns": time.time_ns(), "source": "test",
                                                          "info": {}}).status_code in (200, 201, 204)
        poll(lambda: database.stat().st_mtime_ns != written, timeout_s=5)  # checkpointed
    finally:
        orchestrator.close()

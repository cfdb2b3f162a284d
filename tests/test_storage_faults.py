"""Storage faults are loud and lose nothing: a full disk or a read-only database turns
/health into 503 with the reason, results wait in a bounded queue, and once the disk takes writes
again every one of them is stored; a database that cannot be opened for writing is refused at
start-up with one line. The database lives on a small tmpfs the test mounts."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import zmq

from esiaf.results import make_result
from esiaf.tools.testing import REPO, Orchestrator, poll, signed_result

BASE_NS = 1_763_720_000_000_000_000


@pytest.fixture
def small_disk(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    # 32 MB: room for the database and its write-ahead log before the test fills the rest
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32m", "tmpfs", str(disk)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    (disk / "filler").touch()  # made now: opening it later must not need space the database may have taken
    yield disk
    subprocess.run(["umount", "-l", str(disk)], check=False)


class Pusher:
    def __init__(self, orchestrator):
        body = {"name": "asr", "kind": "speech"}
        registration = self.registration = orchestrator.http.post("/components", json=body).json()
        self.context = zmq.Context()
        self.push = self.context.socket(zmq.PUSH)
        self.push.setsockopt(zmq.LINGER, 0)
        self.push.connect(registration["results_endpoint"])
        self.sent = 0

    def send(self, count: int, text: str = "x" * 200) -> None:
        for _ in range(count):
            self.sent += 1
            result = make_result("asr", "speech", "s", (BASE_NS + self.sent * 10**9, BASE_NS + self.sent * 10**9 + 5),
                                 self.sent, speech={"hypotheses": [{"text": text, "probability": 0.5}]})
            self.push.send_multipart(signed_result(self.registration, result))

    def close(self):
        self.push.close()
        self.context.term()


def stored(orchestrator) -> int:
    """Results of stream s in the database, paged through (1,000 a page)."""
    count, after_id = 0, 0
    while True:
        page = orchestrator.http.get("/results", params={"stream": "s", "limit": 1000, "after_id": after_id}).json()
        count += len(page["items"])
        if not page["items"]:
            return count
        after_id = page["next_after_id"]


def fill(disk) -> None:
    """Writes until the disk is full. Unbuffered: a buffered file's close() would flush what the write
    that hit ENOSPC left in its buffer, and raise ENOSPC again (at the ``with`` line: the flaky failure)."""
    with open(disk / "filler", "r+b", buffering=0) as out:
        try:
            while True:
                out.write(b"\0" * 65536)
        except OSError:
            pass


def test_a_full_disk_is_unhealthy_and_nothing_is_lost_once_space_returns(small_disk):
    orchestrator = Orchestrator(small_disk)
    pusher = Pusher(orchestrator)
    try:
        pusher.send(100)
        poll(lambda: stored(orchestrator) == 100, timeout_s=20)
        fill(small_disk)
        pusher.send(2000)
        health = poll(lambda: (r := orchestrator.http.get("/health")).status_code == 503 and r, timeout_s=20)
        assert "cannot be written" in health.json()["detail"]
        (small_disk / "filler").unlink()
        poll(lambda: orchestrator.http.get("/health").status_code == 200, timeout_s=20)
        poll(lambda: stored(orchestrator) == 2100, timeout_s=20)
    finally:
        pusher.close()
        orchestrator.close()


def test_a_read_only_database_is_refused_at_start_up_with_one_line(small_disk, tmp_path):
    orchestrator = Orchestrator(small_disk)  # makes the database
    orchestrator.close()
    read_only = tmp_path / "ro"
    read_only.mkdir()
    subprocess.run(["mount", "--bind", "-o", "ro", str(small_disk), str(read_only)], check=True)
    try:
        started = subprocess.run(
            [sys.executable, "-m", "esiaf_services.orchestrator", "--port", "0", "--db", str(read_only / "o.db")],
            cwd=REPO, capture_output=True, text=True, timeout=60,
            env={**os.environ, "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0", "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"})
    finally:
        subprocess.run(["umount", str(read_only)], check=False)
    assert started.returncode == 2
    assert "cannot use database" in started.stderr and "Traceback" not in started.stderr

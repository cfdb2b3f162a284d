"""A corrupt database: refused at start-up with one line naming --recover; --recover
copies what SQLite can still read into a new file, keeps the damaged one and starts on the copy.

The databases are real: written by the real orchestrator (a process), then damaged on disk (pages in
the middle overwritten with random bytes, or the file cut short); and, for the row-skipping itself,
a table whose first, a middle or its last leaf page is overwritten."""
from __future__ import annotations

import hashlib
import os
import random
import re
import sqlite3
import subprocess
import sys

import pytest
import zmq

from esiaf.tools.testing import REPO, Orchestrator, free_port, poll
from esiaf_services.orchestrator.store.recover import MAX_ROWID, MIN_ROWID, recover
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body
from esiaf_services.orchestrator.tests.test_orchestrator_cli import (
    assert_one_clear_line,
    orchestrator_env,
    run_orchestrator,
)

SEED = 20261123
SENT = 600
BASE_NS = 1_763_720_000_000_000_000
PAGE = 4096


def text_of(n: int) -> str:
    return f"utterance {n} " + "word " * 60


def stored_results(orchestrator: Orchestrator) -> dict[int, str]:
    """sequence -> text of every stored result of stream s, paged through."""
    found: dict[int, str] = {}
    after_id = 0
    while True:
        page = orchestrator.http.get("/results", params={"stream": "s", "limit": 1000, "after_id": after_id}).json()
        if not page["items"]:
            return found
        for item in page["items"]:
            found[item["sequence"]] = item["speech"]["hypotheses"][0]["text"]
        after_id = page["next_after_id"]


def send(component: FakeComponent, numbers: range) -> None:
    for n in numbers:
        component.sequence = n - 1
        component.send_result(stream_id="s", start_ns=BASE_NS + n * 10**9, end_ns=BASE_NS + n * 10**9 + 5 * 10**8,
                              text=text_of(n))


def overwrite_middle(path) -> None:
    """Pages from 40 % to 55 % of the file overwritten with random bytes."""
    rng = random.Random(SEED)
    pages = path.stat().st_size // PAGE
    with path.open("r+b") as out:
        for page in range(int(pages * 0.40), int(pages * 0.55)):
            out.seek(page * PAGE)
            out.write(rng.randbytes(PAGE))


def cut_short(path) -> None:
    """The file cut at 60 %, in the middle of a page."""
    os.truncate(path, int(path.stat().st_size * 0.6) + 1000)


@pytest.fixture
def zctx():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.mark.parametrize("damage", [overwrite_middle, cut_short], ids=["garbage pages", "truncated"])
def test_a_corrupt_database_is_refused_and_recover_starts_on_what_survived(damage, tmp_path, zctx):
    orchestrator = Orchestrator(tmp_path)
    try:
        asr = FakeComponent(zctx, orchestrator.http, component_body("asr", kind="speech"))
        send(asr, range(1, SENT + 1))
        poll(lambda: len(stored_results(orchestrator)) == SENT, timeout_s=30)
        asr.close()
        orchestrator.process.terminate()
        assert orchestrator.process.wait(timeout=20) == 0
        sqlite3.connect(orchestrator.db_path).close()  # the write-ahead log, if any, into the file
        damage(orchestrator.db_path)
        damaged = hashlib.sha256(orchestrator.db_path.read_bytes()).hexdigest()

        refused = run_orchestrator(["--port", "0", "--db", str(orchestrator.db_path)],
                                   orchestrator_env(control_port="0", results_port="0"))
        assert_one_clear_line(refused, "is corrupt", "--recover")

        orchestrator.start("--recover")
        (kept,) = [p for p in tmp_path.glob("o.db.corrupt-*") if not p.name.endswith(("-wal", "-shm"))]
        assert hashlib.sha256(kept.read_bytes()).hexdigest() == damaged  # kept as it was
        survived = stored_results(orchestrator)
        assert 0 < len(survived) < SENT
        assert all(survived[n] == text_of(n) for n in survived)  # what is served is what was sent
        if damage is overwrite_middle:  # rows after the damage are kept, not only those before it
            assert max(survived) == SENT and len(survived) < max(survived)
        log = (tmp_path / "orchestrator.log").read_text()
        said = re.search(r"orchestrator: recovered results: (\d+) rows; lost: (.+)", log)
        assert said and int(said.group(1)) == len(survived), log
        assert "event=db_table_recovered table=results" in log
        served = orchestrator.http.get("/health").json()["recovered"]  # what esiaf run --recover shows
        assert served[0].startswith(f"database {orchestrator.db_path} was corrupt") and said.group(0).split(
            "orchestrator: ")[1] in served, served

        asr = FakeComponent(zctx, orchestrator.http, component_body("asr", kind="speech"))
        send(asr, range(SENT + 1, SENT + 11))  # the recovered database takes new results
        poll(lambda: len(stored_results(orchestrator)) == len(survived) + 10, timeout_s=30)
        asr.close()
    finally:
        orchestrator.close()


def test_recover_leaves_a_sound_database_alone(tmp_path):
    path = tmp_path / "sound.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE t (x)")
    before = path.read_bytes()
    assert recover(path) is None and recover(tmp_path / "absent.db") is None
    assert path.read_bytes() == before and list(tmp_path.iterdir()) == [path]


def leaves(path) -> list[tuple[int, int]]:
    """(page number, cells) of table t's leaf pages, in rowid order."""
    with sqlite3.connect(path) as db:
        return db.execute("SELECT pageno, ncell FROM dbstat WHERE name = 't' AND pagetype = 'leaf'"
                          " ORDER BY path").fetchall()


@pytest.mark.parametrize("which", ["first", "middle", "last"])
def test_exactly_the_rows_of_a_damaged_leaf_are_lost(which, tmp_path):
    path = tmp_path / "t.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE t (id INTEGER PRIMARY KEY, x TEXT NOT NULL)")
        db.executemany("INSERT INTO t (x) VALUES (?)", [(f"row {n} " + "y" * 300,) for n in range(1, 3001)])
    pages = leaves(path)
    index = {"first": 0, "middle": len(pages) // 2, "last": len(pages) - 1}[which]
    first_lost = sum(cells for _, cells in pages[:index]) + 1
    lost = set(range(first_lost, first_lost + pages[index][1]))
    with path.open("r+b") as out:
        out.seek((pages[index][0] - 1) * PAGE)
        out.write(random.Random(SEED).randbytes(PAGE))

    recovery = recover(path)

    with sqlite3.connect(path) as db:
        ids = {row[0] for row in db.execute("SELECT id FROM t")}
        assert all(x.startswith(f"row {n} ") for n, x in db.execute("SELECT id, x FROM t"))
    assert ids == set(range(1, 3001)) - lost
    (table,) = recovery.tables
    assert table.rows == 3000 - len(lost) and table.damaged == 0
    (start, end), = table.unreadable
    assert start <= min(lost) and end >= max(lost)  # the range bounds what was lost
    assert (start == MIN_ROWID) == (which == "first") and (end == MAX_ROWID) == (which == "last")
    assert recovery.kept.exists()


def corrupt_workdir(tmp_path) -> None:
    path = tmp_path / "esiaf.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE t (x TEXT)")
        db.executemany("INSERT INTO t VALUES (?)", [("y" * 300,)] * 100)
    with path.open("r+b") as out:  # a page in the middle
        out.seek(4 * PAGE)
        out.write(random.Random(SEED).randbytes(PAGE))


def esiaf_run(tmp_path, *options: str, timeout_s: float) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf", "run",
                           "--input", str(REPO / "examples/robocup_questions.wav"),
                           "--port", str(free_port()), "--workdir", str(tmp_path), *options],
                          cwd=REPO, env=orchestrator_env(), capture_output=True, text=True, timeout=timeout_s)


def test_esiaf_run_on_a_corrupt_workdir_names_recover(tmp_path):
    """The launcher stops at the orchestrator (nothing else is started) and shows its one line."""
    corrupt_workdir(tmp_path)
    run = esiaf_run(tmp_path, timeout_s=60)
    assert run.returncode != 0 and "service orchestrator exited with code 2" in run.stderr, run.stderr
    assert "is corrupt" in run.stderr and "--recover" in run.stderr


@pytest.mark.e2e
def test_esiaf_run_recover_says_what_it_recovered_and_runs(tmp_path):
    corrupt_workdir(tmp_path)
    run = esiaf_run(tmp_path, "--recover", "--fast", "--grammar", "robocup", "--without", "emotion,gender,voiceid",
                    timeout_s=300)
    assert run.returncode == 0, run.stderr
    said = [line for line in run.stderr.splitlines() if line.startswith("esiaf: --recover: ")]
    assert said[0].startswith(f"esiaf: --recover: database {tmp_path / 'esiaf.db'} was corrupt"), run.stderr
    assert any(re.match(r"esiaf: --recover: recovered t: \d+ rows; lost: ", line) for line in said), said
    assert list(tmp_path.glob("esiaf.db.corrupt-*")), "the damaged file is kept"
    assert "how big is the rcmp" in run.stdout.lower(), run.stdout  # the run went on: a recognised question

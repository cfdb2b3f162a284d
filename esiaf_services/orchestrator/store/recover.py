"""``--recover``: what SQLite can still read of a corrupt database, copied into a new file.

The damaged file is kept beside it (``esiaf.db.corrupt-20261123T114500Z``, its ``-wal`` and
``-shm`` too) and the orchestrator starts on the copy. A sound database is left as it is, so
``--recover`` is safe on every start.

Debian 12's ``sqlite3`` command has ``.recover``, but there it fails ("SQL logic error"): the
system library it uses is built without the ``sqlite_dbpage`` table that ``.recover`` reads. So
the copy is made here through Python's sqlite3: the schema as it was (tables, indexes,
``user_version``), then each table in rowid order, 500 rows a read and, where a read fails, one row
at a time up to the damage. A damaged page makes reading fail at the rowids it held; those are
skipped by seeking ever further ahead until a seek succeeds, then bisecting back to the first rowid
that can be read, so the rows after the damage are kept. A row that is read but breaks a
constraint, or whose JSON does not parse, is dropped and counted. A file cut short is read as far
as it goes (``writable_schema``, as ``.recover`` does).
"""
from __future__ import annotations

import logging
import os
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from .database import corruption, is_corrupt_error, remove_db_files

log = logging.getLogger(__name__)

MIN_ROWID, MAX_ROWID = -2**63, 2**63 - 1
BATCH_ROWS = 500
# columns that hold JSON the orchestrator parses or serves as it is
JSON_COLUMNS = {"results": ["json"], "fused": ["json"], "streams": ["info"],
                "pending_fusions": ["settings", "waiting"]}


class RecoveryError(Exception):
    """The copy could not be made (e.g. the folder cannot be written): the message says why."""


@dataclass
class TableReport:
    name: str
    rows: int = 0  # copied
    damaged: int = 0  # read, but refused: a constraint failed or its JSON did not parse
    unreadable: list[tuple[int, int]] = field(default_factory=list)  # rowid ranges that could not be read

    def skip(self, first: int, last: int) -> None:
        if self.unreadable and self.unreadable[-1][1] + 1 == first:  # one range, not one per probe
            first = self.unreadable.pop()[0]
        self.unreadable.append((first, last))

    def lost(self) -> str:
        if not self.unreadable and not self.damaged:
            return "nothing lost"
        parts = [f"{'all rows' if (a, b) == (MIN_ROWID, MAX_ROWID) else _span(a, b)} unreadable"
                 for a, b in self.unreadable]
        if self.damaged:
            parts.append(f"{self.damaged} damaged rows dropped")
        return "lost: " + ", ".join(parts)


def _span(first: int, last: int) -> str:
    if first == MIN_ROWID:
        return f"rowids up to {last}"
    if last == MAX_ROWID:
        return f"rowids from {first}"
    return f"rowid {first}" if first == last else f"rowids {first}..{last}"


@dataclass
class Recovery:
    path: Path
    kept: Path  # the damaged file, renamed
    problem: str  # what SQLite found wrong
    tables: list[TableReport]
    schema_readable: bool

    def lines(self) -> list[str]:
        head = (f"database {self.path} was corrupt ({self.problem}); copied what could be read into a new "
                f"{self.path.name}, the damaged file kept as {self.kept.name}")
        if not self.schema_readable:
            return [head, "its schema could not be read: nothing recovered, the orchestrator starts on an empty "
                          "database"]
        return [head] + [f"recovered {t.name}: {t.rows} rows; {t.lost()}" for t in self.tables]


def recover(path: str | Path) -> Recovery | None:
    """Recovers the database at ``path`` if it is corrupt; None if it is absent or sound."""
    path = Path(path)
    if not path.exists():
        return None
    problem = _problem(path)
    if problem is None:
        log.info("event=db_sound path=%s recover=nothing_to_do", path)
        return None
    partial = path.with_name(path.name + ".recovering")
    kept = path.with_name(f"{path.name}.corrupt-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")
    try:
        remove_db_files(partial)  # of a recovery that was interrupted
        # read-only: the damaged file (and its write-ahead log) stay exactly as they were
        old = sqlite3.connect(f"file:{quote(str(path.resolve()))}?mode=ro", uri=True)
        new = sqlite3.connect(partial, isolation_level=None)
        try:
            tables = _copy(old, new)
        finally:
            old.close()
            new.close()
        for suffix in ("-wal", "-shm", ""):  # the database last: until then a crash leaves it in place
            if Path(f"{path}{suffix}").exists():
                os.replace(f"{path}{suffix}", f"{kept}{suffix}")
        os.replace(partial, path)
    except (OSError, sqlite3.Error) as exc:
        raise RecoveryError(f"cannot recover database {path}: {exc}") from None
    recovery = Recovery(path=path, kept=kept, problem=problem, tables=tables or [],
                        schema_readable=tables is not None)
    log.warning("event=db_recovered path=%s kept=%s problem=%r schema_readable=%s",
                path, kept, problem, recovery.schema_readable)
    for table in recovery.tables:
        log.warning("event=db_table_recovered table=%s rows=%d damaged=%d unreadable_rowids=%s",
                    table.name, table.rows, table.damaged,
                    ",".join(f"{a}..{b}" for a, b in table.unreadable) or "-")
    return recovery


def _problem(path: Path) -> str | None:
    try:
        db = sqlite3.connect(f"file:{quote(str(path.resolve()))}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise RecoveryError(f"cannot open database {path}: {exc}") from None
    try:
        return corruption(db)
    except sqlite3.DatabaseError as exc:
        if is_corrupt_error(exc):
            return str(exc)
        raise RecoveryError(f"cannot check database {path}: {exc}") from None
    finally:
        db.close()


def _copy(old: sqlite3.Connection, new: sqlite3.Connection) -> list[TableReport] | None:
    """The schema and every table's readable rows; None if the schema itself cannot be read."""
    # as .recover does: also lets SQLite read a file shorter than its header says (cut short)
    old.execute("PRAGMA writable_schema = ON")
    try:
        version = old.execute("PRAGMA user_version").fetchone()[0]
        schema = old.execute("SELECT type, name, sql FROM sqlite_master WHERE sql IS NOT NULL"
                             " AND name NOT LIKE 'sqlite_%' ORDER BY type = 'index', rowid").fetchall()
    except sqlite3.DatabaseError:
        return None
    new.execute(f"PRAGMA user_version = {int(version)}")
    for _, _, sql in schema:  # tables, then indexes: a row that breaks a unique index is refused
        new.execute(sql)
    reports = []
    for kind, name, _ in schema:
        if kind == "table":
            new.execute("BEGIN")
            reports.append(_copy_table(old, new, name))
            new.execute("COMMIT")
    return reports


def _copy_table(old: sqlite3.Connection, new: sqlite3.Connection, table: str) -> TableReport:
    report = TableReport(table)
    quoted = _quote(table)
    names = [_quote(row[1]) for row in old.execute(f"PRAGMA table_info({quoted})")]  # from the schema
    columns = ", ".join(names)
    select = f"SELECT rowid, {columns} FROM {quoted} WHERE rowid >= ? ORDER BY rowid"
    insert = f"INSERT INTO {quoted} (rowid, {columns}) VALUES ({', '.join('?' * (len(names) + 1))})"
    checks = [f"json_valid({_quote(column)})" for column in JSON_COLUMNS.get(table, [])]
    start: int | None = MIN_ROWID  # the next rowid to read; None once the end is reached
    while start is not None:
        try:  # a batch at a time; where it fails, one row at a time up to the damage
            rows = old.execute(select + f" LIMIT {BATCH_ROWS}", (start,)).fetchall()
        except sqlite3.DatabaseError:
            try:
                rows = old.execute(select + " LIMIT 1", (start,)).fetchall()
            except sqlite3.DatabaseError:
                resume = _next_readable(old, select, start)
                report.skip(start, MAX_ROWID if resume is None else resume - 1)
                start = resume
                continue
        if not rows:
            break
        before = start
        for row in rows:
            if row[0] < start:  # a damaged page can hand out rowids out of order
                continue
            try:
                new.execute(insert, row)
            except sqlite3.Error:
                report.damaged += 1
            start = row[0] + 1 if row[0] < MAX_ROWID else None
            if start is None:
                break
        if start == before:  # nothing but rowids already passed: the rest cannot be trusted
            report.skip(start, MAX_ROWID)
            break
    if checks:
        report.damaged += new.execute(f"DELETE FROM {quoted} WHERE NOT ({' AND '.join(checks)})").rowcount
    report.rows = new.execute(f"SELECT COUNT(*) FROM {quoted}").fetchone()[0]
    return report


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _next_readable(old: sqlite3.Connection, select: str, start: int) -> int | None:
    """The first rowid after ``start`` from which reading works again; None if none does."""
    def readable(rowid: int) -> bool:
        try:
            old.execute(select + " LIMIT 1", (rowid,)).fetchone()
            return True
        except sqlite3.DatabaseError:
            return False

    failed, step = start, 1
    while not readable(good := min(start + step, MAX_ROWID)):  # ever further ahead
        if good == MAX_ROWID:
            return None
        failed, step = good, step * 2
    while good - failed > 1:  # bisect: the first readable rowid lies in (failed, good]
        middle = (failed + good) // 2
        if readable(middle):
            good = middle
        else:
            failed = middle
    return good

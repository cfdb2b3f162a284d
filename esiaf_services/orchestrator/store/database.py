"""SQLite store of every result and every fused result.

One connection, owned by the event loop thread; writes are batched into one
transaction per batch of received messages. The schema is versioned with
``PRAGMA user_version``: ``MIGRATIONS[i]`` (schema.py) brings a database from version i to i + 1.
JSON is stored ready to send, so queries hand out stored text without re-encoding it.
"""
from __future__ import annotations

import logging
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from .schema import MIGRATIONS  # also imported from here (tests)

log = logging.getLogger(__name__)


class StoreError(Exception):
    """The database cannot be opened or migrated: the message says why."""


CORRUPT_CODES = (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
RECOVER_HINT = ("start with --recover to copy what SQLite can still read into a new file "
                "(the damaged one is kept)")


def corruption(db: sqlite3.Connection) -> str | None:
    """The first problem ``PRAGMA quick_check`` finds (it reads every page: 0.3 s for 430 MB cached),
    or None if the database is sound; raises sqlite3.DatabaseError if the check cannot run."""
    first = db.execute("PRAGMA quick_check(1)").fetchone()[0]
    return None if first == "ok" else " ".join(first.replace("*** in database main ***", "").split())


def is_corrupt_error(exc: sqlite3.Error) -> bool:
    return (getattr(exc, "sqlite_errorcode", 0) & 0xFF) in CORRUPT_CODES


@dataclass(frozen=True)
class Page:
    """Stored JSON texts, oldest first, and the id to pass as ``after_id`` for the next page."""

    items: list[str]
    next_after_id: int | None
    revisions: dict[int, int] = field(default_factory=dict)  # fused results: id -> revision

    def to_json(self) -> str:
        after = "null" if self.next_after_id is None else str(self.next_after_id)
        return '{"items":[' + ",".join(self.items) + '],"next_after_id":' + after + "}"


def remove_db_files(path: Path) -> None:
    for suffix in ("", "-journal", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


class StoreUnavailable(Exception):
    """The database cannot be written now; the writes stay queued."""


class Store:
    def __init__(self, path: str | Path, *, fresh: bool = False, max_queued: int = 100_000,
                 on_written: Callable[[], object] = lambda: None) -> None:
        """``on_written``: called after every write, from the thread that wrote (the checkpoint task
        waits for one)."""
        path = Path(path)
        self._queued: list[tuple[str, tuple]] = []
        self._batch_start = 0
        self.max_queued = max_queued
        self.lost_writes = 0
        self.error: str | None = None  # why the last commit failed; None while writes succeed
        self.on_written = on_written
        try:
            if fresh:
                remove_db_files(path)
            self._db = sqlite3.connect(path, isolation_level=None)
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"cannot open database {path}: {exc}") from None
        try:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            # No checkpoint inside a commit (its fsync takes milliseconds): Checkpointer
            # does it off the event loop.
            self._db.execute("PRAGMA wal_autocheckpoint=0")
            problem = corruption(self._db)
            if problem is not None:
                raise StoreError(f"database {path} is corrupt ({problem}); {RECOVER_HINT}")
            self._migrate(path)
            self.next_result_id = self._db.execute(
                "SELECT COALESCE(MAX(id), 0) + 1 FROM results").fetchone()[0]
            self.next_seq = self._db.execute(
                "SELECT COALESCE(MAX(seq), 0) + 1 FROM fused").fetchone()[0]
            self.next_fused_id = self._db.execute(  # pending fusions hold their ids already
                "SELECT MAX((SELECT COALESCE(MAX(id), 0) FROM fused),"
                " (SELECT COALESCE(MAX(fused_id), 0) FROM pending_fusions)) + 1").fetchone()[0]
        except StoreError:
            self._db.close()
            raise
        except sqlite3.Error as exc:
            self._db.close()
            if is_corrupt_error(exc):
                raise StoreError(f"database {path} is corrupt ({exc}); {RECOVER_HINT}") from None
            raise StoreError(f"cannot use database {path}: {exc}") from None
        self.path = path

    def _migrate(self, path: Path) -> None:
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version > len(MIGRATIONS):
            raise StoreError(f"database {path} has schema version {version}, newer than this "
                             f"orchestrator knows ({len(MIGRATIONS)}); use a newer orchestrator "
                             "or another --db")
        for target in range(version + 1, len(MIGRATIONS) + 1):
            # user_version is not a bound parameter; target is our own integer.
            self._db.executescript(
                f"BEGIN; {MIGRATIONS[target - 1]} PRAGMA user_version = {int(target)}; COMMIT;")
            log.info("event=db_migrated path=%s schema_version=%d", path, target)

    def close(self) -> None:
        self._db.close()

    def secret(self, name: str, make: Callable[[], bytes]) -> bytes:
        """The secret kept under ``name``, made (and written at once) the first time; a database that
        cannot be written now gives one for this run only (logged)."""
        row = self._db.execute("SELECT value FROM secrets WHERE name = ?", (name,)).fetchone()
        if row is not None:
            return bytes(row[0])
        value = make()
        try:
            self._db.execute("INSERT INTO secrets (name, value) VALUES (?, ?)", (name, value))
        except sqlite3.Error as exc:
            log.warning("event=secret_not_kept name=%s reason=%s", name, exc)
        return value

    # writes: call begin(), the add_* methods, then commit(). The writes wait in memory until
    # commit() runs them in one transaction; if the database cannot take them (disk full, file
    # read-only) they stay queued (at most max_queued, the oldest then counted lost) and every
    # later commit() tries them again, so nothing is lost when the disk comes back.
    def begin(self) -> None:
        self._batch_start = len(self._queued)

    @property
    def changes(self) -> int:
        """Rows written since the database was opened (SQLite's total_changes)."""
        return self._db.total_changes

    def commit(self) -> None:
        if not self._queued:
            return
        try:
            self._db.execute("BEGIN")
            for sql, params in self._queued:
                self._db.execute(sql, params)
            self._db.execute("COMMIT")
            self.on_written()
        except sqlite3.Error as exc:
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            overflow = len(self._queued) - self.max_queued
            if overflow > 0:
                del self._queued[:overflow]
                self.lost_writes += overflow
            if self.error is None:
                log.error("event=store_unwritable path=%s error=%s queued=%d", self.path, exc, len(self._queued))
            self.error = f"database {self.path} cannot be written: {exc} ({len(self._queued)} writes queued, " \
                         f"{self.lost_writes} lost)"
            raise StoreUnavailable(self.error) from None
        if self.error is not None:
            log.warning("event=store_writable_again path=%s written=%d", self.path, len(self._queued))
        self.error = None
        self._queued.clear()

    def rollback(self) -> None:
        """Forgets the writes since begin() (the work that made them failed)."""
        del self._queued[self._batch_start:]

    # one message inside a batch: its writes are undone alone if it fails
    def savepoint(self) -> int:
        return len(self._queued)

    def rollback_savepoint(self, mark: int) -> None:
        del self._queued[mark:]

    @property
    def queued(self) -> int:
        return len(self._queued)

    def _write(self, sql: str, params: tuple) -> None:
        self._queued.append((sql, params))

    def allocate_result_id(self) -> int:
        result_id, self.next_result_id = self.next_result_id, self.next_result_id + 1
        return result_id

    def allocate_fused_id(self) -> int:
        fused_id, self.next_fused_id = self.next_fused_id, self.next_fused_id + 1
        return fused_id

    def add_result(self, *, result_id: int, component: str, type_name: str, stream_id: str,
                   start_ns: int, end_ns: int, produced_ns: int, received_ns: int,
                   proto: bytes, json_text: str) -> None:
        self._write(
            "INSERT INTO results (id, component, type, stream_id, start_ns, end_ns, produced_ns,"
            " received_ns, proto, json) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (result_id, component, type_name, stream_id, start_ns, end_ns, produced_ns,
             received_ns, proto, json_text))

    def allocate_seq(self) -> int:
        """The next publication number (every revision of every fused result gets one)."""
        seq, self.next_seq = self.next_seq, self.next_seq + 1
        return seq

    def add_fused(self, *, fused_id: int, revision: int, fusion: str, stream_id: str,
                  start_ns: int, end_ns: int, published_ns: int, json_text: str,
                  seq: int | None = None) -> None:
        self._write(
            "INSERT INTO fused (id, revision, fusion, stream_id, start_ns, end_ns, published_ns,"
            " json, seq) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (fused_id, revision, fusion, stream_id, start_ns, end_ns, published_ns, json_text,
             self.allocate_seq() if seq is None else seq))

    def add_pending(self, *, fused_id: int, anchor_id: int, settings_json: str,
                    waiting_json: str, opened_ns: int) -> None:
        self._write(
            "INSERT INTO pending_fusions (fused_id, anchor_id, settings, waiting, opened_ns)"
            " VALUES (?, ?, ?, ?, ?)", (fused_id, anchor_id, settings_json, waiting_json, opened_ns))

    def remove_pending(self, fused_id: int) -> None:
        self._write("DELETE FROM pending_fusions WHERE fused_id = ?", (fused_id,))

    def put_latency(self, *, component: str, count: int, mean_ns: float, updated_ns: int) -> None:
        self._write(
            "INSERT INTO latency (component, count, mean_ns, updated_ns) VALUES (?, ?, ?, ?)"
            " ON CONFLICT (component) DO UPDATE SET count = excluded.count,"
            " mean_ns = excluded.mean_ns, updated_ns = excluded.updated_ns",
            (component, count, mean_ns, updated_ns))

    def put_stream(self, *, stream_id: str, start_ns: int, source: str, announced_ns: int,
                   info_json: str) -> None:
        """Records (or re-records) a stream; autocommits, so call it outside begin()/commit()."""
        self._db.execute(
            "INSERT INTO streams (stream_id, start_ns, source, announced_ns, info) VALUES (?, ?, ?, ?, ?)"
            " ON CONFLICT (stream_id) DO UPDATE SET start_ns = excluded.start_ns, source = excluded.source,"
            " announced_ns = excluded.announced_ns, info = excluded.info",
            (stream_id, start_ns, source, announced_ns, info_json))
        self.on_written()

    def streams(self, stream_id: str | None = None) -> list[tuple[str, int, str, int, str]]:
        """(stream_id, start_ns, source, announced_ns, info JSON), oldest announcement first."""
        sql = "SELECT stream_id, start_ns, source, announced_ns, info FROM streams"
        if stream_id is None:
            return self._db.execute(sql + " ORDER BY announced_ns").fetchall()
        return self._db.execute(sql + " WHERE stream_id = ?", (stream_id,)).fetchall()

    def put_policy(self, stream_id: str, policy: str, set_ns: int) -> None:
        """Records a stream's barge-in policy; autocommits, so call it outside begin()/commit()."""
        self._db.execute(
            "INSERT INTO barge_in_policies (stream_id, policy, set_ns) VALUES (?, ?, ?)"
            " ON CONFLICT (stream_id) DO UPDATE SET policy = excluded.policy, set_ns = excluded.set_ns",
            (stream_id, policy, set_ns))
        self.on_written()

    def policies(self) -> dict[str, str]:
        """Every stream's barge-in policy that was set."""
        return dict(self._db.execute("SELECT stream_id, policy FROM barge_in_policies").fetchall())

    # reads
    def latencies(self) -> list[tuple[str, int, float]]:
        """(component, count, mean_ns) of every component that ever sent a result."""
        return self._db.execute(
            "SELECT component, count, mean_ns FROM latency ORDER BY component").fetchall()

    def recent_latencies_ns(self, component: str, limit: int) -> list[int]:
        """Latencies of the component's last ``limit`` results (as each result's JSON gives it: on
        our clock, corrected by the capturing host's offset)."""
        return [row[0] for row in self._db.execute(
            "SELECT CAST(ROUND(json_extract(json, '$.latency_ms') * 1000000) AS INTEGER) FROM results"
            " WHERE component = ? ORDER BY id DESC LIMIT ?", (component, limit))]

    def pending(self) -> list[tuple[int, str, str, str]]:
        """(fused_id, anchor JSON, settings JSON, waiting JSON) of fusions not yet published."""
        return self._db.execute(
            "SELECT p.fused_id, r.json, p.settings, p.waiting FROM pending_fusions AS p"
            " JOIN results AS r ON r.id = p.anchor_id ORDER BY p.fused_id").fetchall()

    def recent(self, memory_ns: int) -> tuple[list[str], list[str]]:
        """JSON of the results and of the latest fused revisions of each stream whose span
        ends within ``memory_ns`` of the stream's newest result: what fusion keeps in memory."""
        results: list[str] = []
        fused: list[str] = []
        for stream_id, newest in self._db.execute(
                "SELECT stream_id, MAX(end_ns) FROM results GROUP BY stream_id").fetchall():
            horizon = newest - memory_ns
            results += [row[0] for row in self._db.execute(
                "SELECT json FROM results WHERE stream_id = ? AND end_ns >= ? ORDER BY id",
                (stream_id, horizon))]
            fused += [row[0] for row in self._db.execute(
                "SELECT json FROM fused WHERE stream_id = ? AND end_ns >= ? AND revision ="
                " (SELECT MAX(f2.revision) FROM fused AS f2 WHERE f2.id = fused.id) ORDER BY id",
                (stream_id, horizon))]
        return results, fused

    def query_results(self, *, type_name: str | None = None, component: str | None = None,
                      stream: str | None = None, start_ns: int | None = None,
                      end_ns: int | None = None, after_id: int | None = None,
                      limit: int = 100) -> Page:
        where, args = _common_filters(stream, start_ns, end_ns, after_id)
        if type_name is not None:
            where.append("type = ?")
            args.append(type_name)
        if component is not None:
            where.append("component = ?")
            args.append(component)
        return self._page("SELECT id, 1, json FROM results", where, args, limit)

    def query_fused(self, *, fusion: str | None = None, stream: str | None = None,
                    start_ns: int | None = None, end_ns: int | None = None,
                    after_id: int | None = None, limit: int = 100, include_robot: bool = True) -> Page:
        """The latest revision of each fused result whose anchor span overlaps the range (without the
        robot's own voice, ``"source": "robot"``, unless ``include_robot``)."""
        where, args = _common_filters(stream, start_ns, end_ns, after_id)
        where.append("revision = (SELECT MAX(f2.revision) FROM fused AS f2 WHERE f2.id = fused.id)")
        if not include_robot:
            where.append(NOT_ROBOT)
        if fusion is not None:
            where.append("fusion = ?")
            args.append(fusion)
        return self._page("SELECT id, revision, json FROM fused", where, args, limit)

    def publications(self, *, after_seq: int, fusion: str | None = None,
                     stream: str | None = None, limit: int = 100, include_robot: bool = True) -> list[tuple[int, str]]:
        """(seq, JSON) of every publication (each revision) after ``after_seq``, in order (without the robot's
        own voice unless ``include_robot``, but for its revisions that follow a person's: they withdraw it)."""
        where, args = _common_filters(stream, None, None, None)
        if not include_robot:  # the robot's revisions that withdraw a person's revision stay
            where.append(f"({NOT_ROBOT} OR {WITHDRAWS})")
        where.append("seq > ?")
        args.append(after_seq)
        if fusion is not None:
            where.append("fusion = ?")
            args.append(fusion)
        return self._db.execute("SELECT seq, json FROM fused WHERE " + " AND ".join(where) +
                                " ORDER BY seq LIMIT ?", [*args, limit]).fetchall()

    def _page(self, select: str, where: list[str], args: list, limit: int) -> Page:
        sql = select + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY id LIMIT ?"
        rows = self._db.execute(sql, [*args, limit]).fetchall()
        return Page(items=[text for _, _, text in rows],
                    next_after_id=rows[-1][0] if rows else None,
                    revisions={row_id: revision for row_id, revision, _ in rows})


# a fused result that is not the robot's own voice (fusion/playback.py); older ones have no source
NOT_ROBOT = "json_extract(json, '$.source') IS NOT 'robot'"
WITHDRAWS = ("EXISTS (SELECT 1 FROM fused AS before WHERE before.id = fused.id AND before.revision = fused.revision - 1"
             " AND json_extract(before.json, '$.source') IS NOT 'robot')")


class Checkpointer:
    """Copies the write-ahead log into the database from a worker thread, so that no commit
    in the event loop waits for a checkpoint's fsync. It reads and writes no rows itself."""

    def __init__(self, path: str | Path) -> None:
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)

    def run(self) -> None:
        """One passive checkpoint (never blocks the writer); call from one thread at a time."""
        self._db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()

    def close(self) -> None:
        self._db.close()


def _common_filters(stream: str | None, start_ns: int | None, end_ns: int | None,
                    after_id: int | None) -> tuple[list[str], list]:
    where: list[str] = []
    args: list = []
    if stream is not None:
        where.append("stream_id = ?")
        args.append(stream)
    if start_ns is not None:  # span overlaps [start_ns, end_ns]
        where.append("end_ns >= ?")
        args.append(start_ns)
    if end_ns is not None:
        where.append("start_ns <= ?")
        args.append(end_ns)
    if after_id is not None:
        where.append("id > ?")
        args.append(after_id)
    return where, args

"""The enrolled voices table: names and speaker embeddings (float32) in the orchestrator's SQLite
file, in a table of their own (``CREATE TABLE IF NOT EXISTS``, on a connection of their own), and
the event long polls of ``GET /voices`` wait on for a change (api/voices.py).

Each embedding row says which encoder made it (``encoder``: ge2e, dvector or fused; a file from
before the column gets it with ``ALTER TABLE``, every older row ``ge2e``, the only encoder then)
and where it came from (``source``: wav, ``wav-room``: a reverberant noisy copy of an enrolled WAV,
span, anonymous, or ``learnt``: posted by a voiceid for an utterance it identified confidently).
Per voice and encoder, the newest MAX_EMBEDDINGS_PER_VOICE enrolled and the newest
MAX_LEARNT_PER_VOICE learnt are kept: learning never pushes out an enrolled embedding."""
from __future__ import annotations

import asyncio
import secrets
import sqlite3
import threading
import time

import numpy as np

MAX_VOICES = 1_000  # enrolled names: a voiceid's result names at most its best few, but every one is scored
MAX_EMBEDDINGS_PER_VOICE = 200  # the oldest of a voice's enrolled embeddings (per encoder) are dropped beyond this
MAX_LEARNT_PER_VOICE = 50  # the oldest of a voice's learnt embeddings (per encoder) are dropped beyond this
LEARNT = "learnt"
ROOM_COPY = "wav-room"  # a WAV enrolment's copy through a simulated room (enrolled, as the WAV itself)
LEGACY_ENCODER = "ge2e"  # every embedding stored before the encoder column was GE2E's


class VoiceLimit(ValueError):
    """An enrolment that would pass MAX_VOICES: the message says so."""


SCHEMA = """
CREATE TABLE IF NOT EXISTS voices (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    embedding BLOB NOT NULL,
    source TEXT NOT NULL,
    added_ns INTEGER NOT NULL,
    encoder TEXT NOT NULL DEFAULT 'ge2e'
);
CREATE INDEX IF NOT EXISTS voices_name ON voices (name);
CREATE TABLE IF NOT EXISTS voices_generation (
    id INTEGER PRIMARY KEY CHECK (id = 0),
    epoch TEXT NOT NULL,
    generation INTEGER NOT NULL
);
"""


class VoiceTable:
    def __init__(self, path: str) -> None:
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=5.0)
        self._db.executescript(SCHEMA)
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(voices)")}
        if "encoder" not in columns:  # a file from before the column: its rows were GE2E's
            self._db.execute(f"ALTER TABLE voices ADD COLUMN encoder TEXT NOT NULL DEFAULT '{LEGACY_ENCODER}'")
        # the ETag: a random epoch per database (a new file never repeats an old one's) and a generation
        # counted up at every change, kept with the voices (a voice deleted and another enrolled in its
        # place, which may take its row id, never repeat an ETag)
        self._db.execute("INSERT OR IGNORE INTO voices_generation VALUES (0, ?, 0)", (secrets.token_hex(4),))
        self._lock = threading.Lock()
        self._changed = asyncio.Event()  # set, and replaced, at every change: long polls wait on it

    def changed(self) -> asyncio.Event:
        """An event set at the next change (add or delete through :meth:`notify`)."""
        return self._changed

    def notify(self) -> None:
        """Wakes the long polls waiting for a change (call it on the event loop)."""
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    def add(self, name: str, embeddings: list[np.ndarray], source: str, encoder: str = LEGACY_ENCODER,
            existing_only: bool = False, room_copies: list[np.ndarray] | None = None) -> int:
        """Adds ``embeddings`` of ``encoder`` (finite: a ValueError if not) to the voice ``name``, a new one
        only while there are fewer than MAX_VOICES (VoiceLimit) and not with ``existing_only`` (then
        KeyError), and in the same transaction ``room_copies``, the embeddings of a WAV's copies (source
        ROOM_COPY); keeps its newest MAX_EMBEDDINGS_PER_VOICE enrolled and MAX_LEARNT_PER_VOICE learnt
        embeddings of that encoder and returns how many older ones of that source were dropped."""
        rows = [(e, source) for e in embeddings] + [(e, ROOM_COPY) for e in room_copies or []]
        if any(not np.isfinite(e).all() for e, _ in rows):
            raise ValueError("an embedding holds NaN or infinity")
        learnt = source == LEARNT
        with self._lock, self._db:  # one transaction: the voices and their generation
            self._db.execute("BEGIN")
            known = self._db.execute("SELECT 1 FROM voices WHERE name = ? LIMIT 1", (name,)).fetchone()
            if known is None and existing_only:
                raise KeyError(name)
            if known is None:
                (count,) = self._db.execute("SELECT COUNT(DISTINCT name) FROM voices").fetchone()
                if count >= MAX_VOICES:
                    raise VoiceLimit(f"{count} voices are enrolled, the most there may be ({MAX_VOICES}): "
                                     f"delete one first")
            self._db.executemany(
                "INSERT INTO voices (name, embedding, source, added_ns, encoder) VALUES (?, ?, ?, ?, ?)",
                [(name, np.asarray(e, "<f4").tobytes(), made, time.time_ns(), encoder) for e, made in rows])
            kind = "source = ?" if learnt else "source != ?"
            dropped = self._db.execute(
                f"DELETE FROM voices WHERE name = ? AND encoder = ? AND {kind} AND id NOT IN "
                f"(SELECT id FROM voices WHERE name = ? AND encoder = ? AND {kind} ORDER BY id DESC LIMIT ?)",
                (name, encoder, LEARNT, name, encoder, LEARNT,
                 MAX_LEARNT_PER_VOICE if learnt else MAX_EMBEDDINGS_PER_VOICE)).rowcount
            self._db.execute("UPDATE voices_generation SET generation = generation + 1")
            return dropped

    def forget_learnt(self, name: str) -> int | None:
        """Deletes the voice's learnt embeddings (every encoder's): how many, None if no such voice."""
        with self._lock, self._db:
            self._db.execute("BEGIN")
            if self._db.execute("SELECT 1 FROM voices WHERE name = ? LIMIT 1", (name,)).fetchone() is None:
                return None
            deleted = self._db.execute("DELETE FROM voices WHERE name = ? AND source = ?", (name, LEARNT)).rowcount
            if deleted:
                self._db.execute("UPDATE voices_generation SET generation = generation + 1")
            return deleted

    def delete(self, name: str) -> int:
        with self._lock, self._db:
            self._db.execute("BEGIN")
            deleted = self._db.execute("DELETE FROM voices WHERE name = ?", (name,)).rowcount
            if deleted:
                self._db.execute("UPDATE voices_generation SET generation = generation + 1")
            return deleted

    def etag(self) -> str:
        with self._lock:
            epoch, generation = self._db.execute("SELECT epoch, generation FROM voices_generation").fetchone()
        return f'"{epoch}-{generation}"'

    def listing(self, embeddings: bool, encoder: str | None = None) -> list[dict]:
        """Each voice: name, count (embeddings), enrolled and learnt (of them), sources, and per encoder
        its enrolled and learnt counts (``encoders``: every encoder's, whatever ``encoder`` says); with
        ``encoder``, only that encoder's embeddings are counted (a voice with none of them is still
        listed, with count 0), without it the most any one encoder has (a WAV embedded by each encoder
        counts once); with ``embeddings``, they too, and ``embedding_sources``: each one's source (wav,
        wav-room, span, anonymous, learnt), in the same order."""
        voices: dict[str, dict] = {}
        with self._lock:  # the sync routes run in a thread pool: one statement at a time
            rows = self._db.execute("SELECT name, embedding, source, encoder FROM voices ORDER BY id").fetchall()
        for name, blob, source, made_by in rows:
            voice = voices.setdefault(name, {"name": name, "count": 0, "enrolled": 0, "learnt": 0, "sources": [],
                                             "encoders": {}})
            per_encoder = voice["encoders"].setdefault(made_by, {"enrolled": 0, "learnt": 0})
            per_encoder["learnt" if source == LEARNT else "enrolled"] += 1
            if embeddings:
                voice.setdefault("embeddings", [])
                voice.setdefault("embedding_sources", [])
            if encoder is not None and made_by != encoder:
                continue
            voice["count"] += 1
            voice["learnt" if source == LEARNT else "enrolled"] += 1
            if source not in voice["sources"]:
                voice["sources"].append(source)
            if embeddings:
                voice["embeddings"].append(np.frombuffer(blob, "<f4").tolist())
                voice["embedding_sources"].append(source)
        if encoder is None:  # an utterance is embedded once per encoder: counted once, by its best-kept encoder
            for voice in voices.values():
                voice["enrolled"] = max(e["enrolled"] for e in voice["encoders"].values())
                voice["learnt"] = max(e["learnt"] for e in voice["encoders"].values())
                voice["count"] = voice["enrolled"] + voice["learnt"]
        return list(voices.values())

    def close(self) -> None:
        self._db.close()

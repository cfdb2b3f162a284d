"""The orchestrator database's schema, versioned with ``PRAGMA user_version``: ``MIGRATIONS[i]``
brings a database from version i to i + 1 (esiaf_services/orchestrator/store/database.py applies them). Only ever
append: a database of any earlier version is brought up to date at start-up."""
from __future__ import annotations

MIGRATIONS: list[str] = [
    # 1: results and fused results
    """
    CREATE TABLE results (
        id INTEGER PRIMARY KEY,
        component TEXT NOT NULL,
        type TEXT NOT NULL,
        stream_id TEXT NOT NULL,
        start_ns INTEGER NOT NULL,
        end_ns INTEGER NOT NULL,
        produced_ns INTEGER NOT NULL,
        received_ns INTEGER NOT NULL,
        proto BLOB NOT NULL,
        json TEXT NOT NULL
    );
    CREATE INDEX results_stream_start ON results (stream_id, start_ns);
    CREATE INDEX results_type ON results (type, id);
    CREATE INDEX results_component ON results (component, id);
    CREATE TABLE fused (
        id INTEGER NOT NULL,
        revision INTEGER NOT NULL,
        fusion TEXT NOT NULL,
        stream_id TEXT NOT NULL,
        start_ns INTEGER NOT NULL,
        end_ns INTEGER NOT NULL,
        published_ns INTEGER NOT NULL,
        json TEXT NOT NULL,
        PRIMARY KEY (id, revision)
    );
    CREATE INDEX fused_stream ON fused (stream_id, id);
    CREATE INDEX fused_fusion ON fused (fusion, id);
    """,
    # 2: streams (capture sessions) as their sources announce them
    """
    CREATE TABLE streams (
        stream_id TEXT PRIMARY KEY,
        start_ns INTEGER NOT NULL,
        source TEXT NOT NULL,
        announced_ns INTEGER NOT NULL,
        info TEXT NOT NULL
    );
    """,
    # 3: fusions waiting to be published, and each component's running mean latency
    """
    CREATE TABLE pending_fusions (
        fused_id INTEGER PRIMARY KEY,
        anchor_id INTEGER NOT NULL,
        settings TEXT NOT NULL,
        waiting TEXT NOT NULL,
        opened_ns INTEGER NOT NULL
    );
    CREATE TABLE latency (
        component TEXT PRIMARY KEY,
        count INTEGER NOT NULL,
        mean_ns REAL NOT NULL,
        updated_ns INTEGER NOT NULL
    );
    CREATE INDEX fused_stream_end ON fused (stream_id, end_ns);
    ALTER TABLE fused ADD COLUMN seq INTEGER;
    UPDATE fused SET seq = rowid;
    CREATE UNIQUE INDEX fused_seq ON fused (seq);
    CREATE INDEX results_stream_end ON results (stream_id, end_ns);
    """,
    # 4: secrets the orchestrator keeps across restarts (what control keys are derived from)
    """
    CREATE TABLE secrets (
        name TEXT PRIMARY KEY,
        value BLOB NOT NULL
    );
    """,
    # 5: per-stream barge-in policies (PUT /streams/{stream}/barge-in), kept across restarts
    """
    CREATE TABLE barge_in_policies (
        stream_id TEXT PRIMARY KEY,
        policy TEXT NOT NULL,
        set_ns INTEGER NOT NULL
    );
    """,
]

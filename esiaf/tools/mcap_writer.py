"""A recording's files: protobuf messages written to MCAP (their schemas embedded), a new file with a
numbered suffix once one reaches its size or time limit (session.mcap, session-2.mcap, ...), and a
write that fails (a full disk) ending the recording with one line, never its caller."""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from pathlib import Path
from typing import IO, Any

from google.protobuf.message import Message
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from esiaf.tools.terminal import err

log = logging.getLogger(__name__)

CHUNK_BYTES = 1024 * 1024  # the mcap library's default chunk: what a reader decompresses at once
MIN_CHUNK_BYTES = 64 * 1024


def part_path(path: Path, number: int) -> Path:
    """The file of a recording's ``number``-th part: the path given first, then <stem>-2<suffix>, ..."""
    return path if number == 1 else path.with_name(f"{path.stem}-{number}{path.suffix}")


def next_part(path: Path) -> int:
    """The number of the first part of ``path`` not written yet: where a restarted recorder goes on."""
    number = 1
    while part_path(path, number).is_file():  # a device (/dev/full) is written again
        number += 1
    return number


class RotatingWriter:
    """Writes messages to ``path`` and its numbered successors. ``max_bytes`` and ``max_s`` (0: no limit)
    bound each file; ``metadata`` is written into every file. Thread-safe. After a failed write
    (``failed`` says why) every later message is dropped."""

    def __init__(self, path: Path, max_bytes: int = 0, max_s: float = 0.0, metadata: dict[str, str] | None = None,
                 compression: CompressionType = CompressionType.LZ4, first_part: int = 1) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.max_s = max_s
        self.metadata = metadata or {}
        self.compression = compression
        self.chunk_bytes = CHUNK_BYTES if not max_bytes else max(MIN_CHUNK_BYTES, min(CHUNK_BYTES, max_bytes // 8))
        self.paths: list[Path] = []
        self.part = first_part - 1  # the number of the part being written
        self.messages = 0
        self.failed = ""
        self._lock = threading.Lock()
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._opened = 0.0
        self._guard(self._open)

    def _open(self) -> None:
        self.part += 1
        path = part_path(self.path, self.part)
        self._file = path.open("wb")
        self.paths.append(path)
        self._writer = Writer(self._file, chunk_size=self.chunk_bytes, compression=self.compression,
                              profile="esiaf")
        self._writer.add_metadata("esiaf", {**self.metadata, "part": str(self.part)})
        self._opened = time.monotonic()
        log.info("recording to %s", path)

    def _close(self) -> None:
        writer, handle = self._writer, self._file
        self._writer, self._file = None, None
        try:
            if writer is not None:
                writer.finish()
        finally:
            if handle is not None:
                handle.close()

    def _due(self) -> bool:
        assert self._file is not None
        return bool((self.max_bytes and self._file.tell() >= self.max_bytes)
                    or (self.max_s and time.monotonic() - self._opened >= self.max_s))

    def write(self, topic: str, message: Message, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Writes one message on ``topic`` at ``log_time_ns`` (its capture time, where it has one)."""
        with self._lock:
            if self._writer is None:
                return

            def write() -> None:
                if self._due():
                    self._close()
                    self._open()
                assert self._writer is not None
                self._writer.write_message(topic, message, log_time=max(0, log_time_ns),
                                           publish_time=publish_time_ns or time.time_ns())
                self.messages += 1

            self._guard(write)

    def close(self) -> None:
        """Finishes the file (its index and footer); a recording that failed is closed as it is."""
        with self._lock:
            self._guard(self._close)

    def _guard(self, action: Any) -> None:
        try:
            action()
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        where = self.paths[-1] if self.paths else self.path
        self.failed = f"cannot write {where}: {exc.strerror or exc}"
        err(f"esiaf: recording stopped ({self.failed}); the pipeline goes on")
        handle, self._writer, self._file = self._file, None, None
        if handle is not None:
            with contextlib.suppress(OSError):  # the same full disk: said above
                handle.close()

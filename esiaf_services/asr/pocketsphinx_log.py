"""Capture pocketsphinx's C log, so its complaints can be put into exception messages.

pocketsphinx logs through C ``stderr`` or a file named by the ``logfn`` config; the destination is
global to the process.  Every recogniser points ``logfn`` at the one file made here (loglevel ERROR,
so it only grows when something goes wrong); ``since(mark)`` returns what was logged after ``mark()``.
"""

from __future__ import annotations

import atexit
import functools
import os
import re
import tempfile
from pathlib import Path

_LOG_PREFIX = re.compile(r'^[A-Z]+: "[^"]*", line \d+: ')


class PocketsphinxLog:
    """A temporary file, removed at exit, that pocketsphinx appends its messages to."""

    def __init__(self) -> None:
        descriptor, name = tempfile.mkstemp(prefix="pocketsphinx-", suffix=".log")
        os.close(descriptor)
        self.path = Path(name)
        atexit.register(self.path.unlink, missing_ok=True)

    def mark(self) -> int:
        return self.path.stat().st_size

    def since(self, mark: int) -> str:
        with self.path.open("rb") as stream:
            stream.seek(mark)
            return stream.read().decode("utf-8", errors="replace").strip()


@functools.cache
def pocketsphinx_log() -> PocketsphinxLog:
    """The process's one pocketsphinx log file."""
    return PocketsphinxLog()


def one_line(text: str) -> str:
    """pocketsphinx's log lines without their 'ERROR: "file.c", line N: ' prefixes, joined on one line."""
    lines = (_LOG_PREFIX.sub("", line).strip() for line in text.splitlines())
    return " / ".join(line for line in lines if line)

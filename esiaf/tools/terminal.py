"""What ``esiaf run`` writes for a person: results on standard output, everything else on standard
error, each line once, and never a reason to stop the pipeline.

A standard output or error that cannot be written (the disk that holds it is full, the pipe it goes
to was closed) is said once on the other stream, if that one works, and is written to no more: the
services go on and the orchestrator stores every result as before (``GET /fused``). Every line
passes :func:`esiaf.printable.printable` here, the one way out: a voice's name, a stream id or a
recognised text with an ANSI escape or a carriage return cannot rewrite the terminal (a line that is
meant to be several is split at its newlines first).
"""
from __future__ import annotations

import os
import sys
from typing import TextIO

from esiaf.printable import printable

_lost: dict[str, int] = {}  # "stdout"/"stderr" that failed: lines not written since


def out(line: str) -> None:
    """A result line on standard output."""
    _write("stdout", line)


def err(line: str) -> None:
    """A status line on standard error."""
    _write("stderr", line)


def lost(name: str) -> int:
    """Lines not written to ``name`` ("stdout" or "stderr") since it failed; 0 while it works."""
    return _lost.get(name, 0)


def _write(name: str, line: str) -> None:
    if name in _lost:
        _lost[name] += 1
        return
    stream: TextIO = getattr(sys, name)
    try:
        stream.write("\n".join(printable(part) for part in line.split("\n")) + "\n")
        stream.flush()
    except (OSError, ValueError) as exc:  # ENOSPC, EPIPE; ValueError: it was closed
        _lost[name] = 1
        _discard(stream)
        other = "stderr" if name == "stdout" else "stdout"
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        what = ("results are still stored (GET /fused) but no more printed" if name == "stdout"
                else "no more status lines are printed")
        if other == "stderr":
            _write(other, f"esiaf: standard output cannot be written ({why}): {what}; the services go on")


def _discard(stream: TextIO) -> None:
    """Points the stream's file descriptor at /dev/null, so that what is still in its buffer, and the
    interpreter's last flush, go nowhere instead of failing again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)
        stream.flush()
    except (OSError, ValueError):
        pass

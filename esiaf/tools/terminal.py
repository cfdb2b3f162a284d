"""What ``esiaf run`` writes for a person: results on standard output, everything else on standard
error, each line once, and never a reason to stop the pipeline.

A standard output or error that cannot be written (the disk that holds it is full, the pipe it goes
to was closed) is said once on the other stream, if that one works, and is written to no more: the
services go on and the orchestrator stores every result as before (``GET /fused``). Every line
passes :func:`esiaf.printable.printable` here, the one way out: a voice's name, a stream id or a
recognised text with an ANSI escape or a carriage return cannot rewrite the terminal (a line that is
meant to be several is split at its newlines first).

A partial result (what a recogniser has heard of an utterance still going on) is shown only on a
terminal, as one line rewritten in place (:func:`partial`); the next line written replaces it.
"""
from __future__ import annotations

import os
import sys
from typing import TextIO

from esiaf.printable import printable

_lost: dict[str, int] = {}  # "stdout"/"stderr" that failed: lines not written since
_partial_shown = False  # a partial line stands on the terminal, without its newline
CLEAR_LINE = "\r\x1b[2K"  # back to the line's start, and erase it


def out(line: str) -> None:
    """A result line on standard output."""
    _write("stdout", line)


def err(line: str) -> None:
    """A status line on standard error."""
    _write("stderr", line)


def terminal_shows_partials() -> bool:
    """Whether standard output is a terminal, where partial results are shown in place."""
    try:
        return sys.stdout.isatty()
    except (ValueError, OSError):
        return False


def partial(line: str) -> None:
    """Shows ``line`` in place of the partial line before it (standard output, a terminal only); ""
    takes it away. The next :func:`out` or :func:`err` line replaces it."""
    global _partial_shown
    if "stdout" in _lost or not terminal_shows_partials():
        return
    try:
        sys.stdout.write(CLEAR_LINE + printable(line)[:max(10, _columns() - 1)])
        sys.stdout.flush()
    except (OSError, ValueError):
        return  # the next full line finds out, and says so
    _partial_shown = bool(line)


def _columns() -> int:
    try:
        return os.get_terminal_size(sys.stdout.fileno()).columns
    except (OSError, ValueError):
        return 80


def lost(name: str) -> int:
    """Lines not written to ``name`` ("stdout" or "stderr") since it failed; 0 while it works."""
    return _lost.get(name, 0)


def _write(name: str, line: str) -> None:
    global _partial_shown
    if name in _lost:
        _lost[name] += 1
        return
    stream: TextIO = getattr(sys, name)
    try:
        if _partial_shown:  # a full line takes the partial one's place
            _partial_shown = False
            sys.stdout.write(CLEAR_LINE)
            sys.stdout.flush()
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

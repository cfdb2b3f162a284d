"""The one rule for text that ESIAF shows a person: control characters escaped; and the one rule for
the names it takes and prints (stream ids, voice names): :func:`name_problem`.

A name or a text that came from a peer (a voice's name, a stream id, a recognised text, a log line)
may hold an ANSI escape or a carriage return, which would rewrite what a terminal shows: a forged
line in place of a real one. Every such character (Unicode categories Cc, Cf, Zl, Zp: C0 and C1
controls, DEL, format characters such as a right-to-left override, line and paragraph separators)
is shown as its Python escape (``\\x1b``, ``\\r``, ``\\u202e``); the rest as it is.
"""
from __future__ import annotations

import unicodedata

CONTROL_CATEGORIES = frozenset({"Cc", "Cf", "Zl", "Zp"})
MAX_NAME_CHARS = 200  # a stream id, a voice's name, a component's name: as the orchestrator bounds them


def control_character(text: str) -> str | None:
    """The first control character of ``text``, or None: what a name must not hold."""
    return next((char for char in text if unicodedata.category(char) in CONTROL_CATEGORIES), None)


def printable(text: object) -> str:
    """``text`` (or its str()) with every control character escaped."""
    text = str(text)
    if control_character(text) is None:
        return text
    return "".join(char.encode("unicode_escape").decode("ascii") if unicodedata.category(char) in CONTROL_CATEGORIES
                   else char for char in text)


def name_problem(name: str, max_chars: int = MAX_NAME_CHARS) -> str | None:
    """Why ``name`` cannot be a name (a stream id, a voice's name), or None: 1 to ``max_chars``
    characters, none of them a control character."""
    if not name:
        return "must not be empty"
    if len(name) > max_chars:
        return f"has {len(name)} characters; at most {max_chars}"
    bad = control_character(name)
    if bad is not None:
        return f"holds the control character U+{ord(bad):04X}; give a printable name"
    return None

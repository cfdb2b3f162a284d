"""The grammar's sentence nearest a transcript, for a grammar too large to list (``GrammarSnapper``).

A closed set of sentences (``matching.py``, ``closed_set.py``) compares a transcript with every
sentence: up to ``MAX_SENTENCES``. A grammar such as RoboCup@Home's GPSR commands (~10⁵ sentences
from a few dozen rules) is searched instead: a weighted edit distance between the transcript's
words and the grammar, computed over the grammar's rules as they stand (never listed), one vector
of costs per node (the cost of having read the transcript's first ``j`` words), so the work grows
with the grammar's size times the transcript's length, not with the number of its sentences
(GPSR category 1: 962 word nodes, ~30 ms for a 12-word transcript on this machine).

Costs: a transcript word the sentence does not have, 1; a word of the sentence the transcript lacks,
0.5 (Whisper drops words in noise: "Simple living room." for "locate the snacks in the living room";
with 1 such a short transcript snaps to the shortest sentences, "give me the spoon", and loses the
place it got right: on 40 GPSR commands of the eval's rooms, pocketsphinx and where it rejects
Whisper's transcript snapped (or rejected past a distance of 0.5), 61 -> 65 of 76 slots right); a
grammar word in place of a transcript word, the letters' edit distance over the longer word's
length (0 when equal; "robin" for "robert" 0.5), at most 1. The nearest sentence is the grammar's
path of least cost; ``Snapped.distance`` is that cost over the words of the longer of the sentence
and the transcript.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from esiaf_services.asr.matching import GrammarError, jsgf_rules, jsgf_tokens, normalise, word_distance

MAX_NODES = 200_000  # word nodes of the grammar with its rules expanded in place: past it, refused
MAX_WORDS = 60  # transcript words searched (Whisper's 30 s window holds at most ~100)
GAP = 1.0  # a word the transcript has that the sentence lacks
LEFT_OUT = 0.5  # a word of the sentence the transcript lacks (Whisper drops words in noise: module docstring)
MAX_DISTANCE = 0.5  # the asr's default whisper.max_snap_distance: a sentence further than this is out of set

Node = tuple  # ("word", str) | ("seq", [Node]) | ("alt", [Node]) | ("opt", Node) | ("ref", str)


@dataclass(frozen=True)
class Snapped:
    sentence: str  # the grammar's sentence nearest the transcript ("" for an empty transcript)
    cost: float  # the edit cost (module docstring)
    words: int  # the sentence's words

    @property
    def distance(self) -> float:
        """The cost per word of the longer of the sentence and the transcript: 0 is the transcript itself."""
        return self.cost / max(1, self.words)


@lru_cache(maxsize=65536)
def substitution(said: str, heard: str) -> float:
    """A grammar word ``said`` for the transcript's ``heard``: their letters' edit distance over the longer
    one's length, at most 1."""
    if said == heard:
        return 0.0
    return min(1.0, word_distance(list(said), list(heard)) / max(len(said), len(heard)))


class GrammarSnapper:
    """A JSGF grammar's public rules as a tree of words, searched for the sentence nearest a transcript."""

    def __init__(self, rules: dict[str, Node], public: list[str], left_out: float = LEFT_OUT,
                 put_in: float = GAP) -> None:
        self.rules, self.public = rules, public
        self.left_out, self.put_in = left_out, put_in  # a grammar word the transcript lacks; a word it adds
        self._sizes: dict[str, int] = {}  # word nodes of each rule, expanded
        self.nodes = sum(self._size(("ref", name), ()) for name in public)
        if self.nodes > MAX_NODES:
            raise GrammarError(f"{self.nodes} words with its rules expanded, more than the {MAX_NODES} searched")

    @classmethod
    def from_jsgf(cls, text: str) -> GrammarSnapper:
        """Alternatives ``|``, sequences, groups ``( )``, optionals ``[ ]``, ``<NULL>`` and rule references;
        repetition, tags and weights are refused, and so is a rule that refers to itself."""
        bodies, public = jsgf_rules(text)
        rules = {}
        for name, body in bodies.items():
            tokens = jsgf_tokens(body)
            node, end = _alternatives(tokens, 0)
            if end != len(tokens):
                raise GrammarError(f"rule <{name}>: unexpected {tokens[end]!r}")
            rules[name] = node
        return cls(rules, public)

    @classmethod
    def from_file(cls, path: Path) -> GrammarSnapper:
        return cls.from_jsgf(Path(path).read_text(encoding="utf-8"))

    def _size(self, node: Node, seen: tuple[str, ...]) -> int:
        kind, value = node
        if kind == "word":
            return 1
        if kind == "ref":
            if value == "NULL":
                return 0
            if value in seen:
                raise GrammarError(f"rule <{value}> refers to itself: no search over it")
            if value not in self.rules:
                raise GrammarError(f"rule <{value}> is not defined")
            if value not in self._sizes:
                self._sizes[value] = self._size(self.rules[value], (*seen, value))
            return self._sizes[value]
        if kind == "opt":
            return self._size(value, seen)
        total = 0
        for child in value:
            total += self._size(child, seen)
            if total > MAX_NODES:
                break
        return total

    def nearest(self, transcript: str) -> Snapped:
        """The grammar's sentence nearest ``transcript`` (its first ``MAX_WORDS`` words)."""
        heard = normalise(transcript)[:MAX_WORDS]
        if not heard:
            return Snapped("", 0.0, 0)
        start = [(j * self.put_in, None) for j in range(len(heard) + 1)]  # the transcript's first j words put in
        best: tuple[float, object] = (math.inf, None)
        for name in self.public:
            end = self._search(("ref", name), start, heard)[-1]
            best = min(best, end, key=lambda pair: pair[0])
        words: list[str] = []
        path: Any = best[1]  # (word, the path before it), or None
        while path is not None:
            words.append(path[0])
            path = path[1]
        words.reverse()
        return Snapped(" ".join(words), best[0], max(len(words), len(heard)))

    def _search(self, node: Node, costs: list, heard: list[str]) -> list:
        """The cheapest way to each ``j`` (the transcript's first ``j`` words read) after ``node``, from
        ``costs`` before it: a list of (cost, path), the path the grammar's words as a linked list."""
        kind, value = node
        if kind == "word":
            gap, put_in = self.left_out, self.put_in
            out = [(costs[0][0] + gap, (value, costs[0][1]))]
            for j in range(1, len(costs)):
                left_out, prev = costs[j], costs[j - 1]
                replaced = prev[0] + substitution(value, heard[j - 1])
                if replaced < left_out[0] + gap:
                    cost, path = replaced, (value, prev[1])
                else:
                    cost, path = left_out[0] + gap, (value, left_out[1])
                before = out[j - 1]  # the transcript's word j put in after this one
                if before[0] + put_in < cost:
                    cost, path = before[0] + put_in, before[1]
                out.append((cost, path))
            return out
        if kind == "seq":
            for child in value:
                costs = self._search(child, costs, heard)
            return costs
        if kind == "alt":
            options = [self._search(child, costs, heard) for child in value]
            return [min(column, key=lambda pair: pair[0]) for column in zip(*options, strict=True)]
        if kind == "opt":
            taken = self._search(value, costs, heard)
            return [a if a[0] <= b[0] else b for a, b in zip(costs, taken, strict=True)]
        if value == "NULL":  # ref
            return costs
        return self._search(self.rules[value], costs, heard)


def _alternatives(tokens: list[str], i: int) -> tuple[Node, int]:
    options = []
    node, i = _sequence(tokens, i)
    options.append(node)
    while i < len(tokens) and tokens[i] == "|":
        node, i = _sequence(tokens, i + 1)
        options.append(node)
    return (options[0] if len(options) == 1 else ("alt", options)), i


def _sequence(tokens: list[str], i: int) -> tuple[Node, int]:
    parts: list[Node] = []
    while i < len(tokens) and tokens[i] not in ("|", ")", "]"):
        token = tokens[i]
        if token in ("*", "+") or token.startswith("{") or token.startswith("/"):
            raise GrammarError(f"{token!r} (repetition, tags or weights) is not supported in grammar search")
        if token in ("(", "["):
            inner, i = _alternatives(tokens, i + 1)
            if i >= len(tokens) or tokens[i] != {"(": ")", "[": "]"}[token]:
                raise GrammarError(f"unbalanced {token!r}")
            parts.append(("opt", inner) if token == "[" else inner)
        elif token.startswith("<"):
            parts.append(("ref", token[1:-1]))
        else:
            parts.extend(("word", word) for word in normalise(token))
        i += 1
    return (parts[0] if len(parts) == 1 else ("seq", parts)), i

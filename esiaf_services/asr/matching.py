"""Closed-set matching: a transcript to the nearest allowed sentence, or "out of set".

The allowed sentences come from a file (one per line) or a finite JSGF grammar expanded into its
sentences. Both sides are normalised (lower case, no punctuation, numbers as words, ordinals too:
"20th" is "twentieth", "mr." as "mister", dotted abbreviations joined: "R.C.M.P." is "rcmp",
apostrophes kept: "what's") and compared two ways:

- word by word with the Levenshtein distance: ``1 - distance / max(len(transcript), len(sentence))``
  in words, 1 for the same sentence, 0 for nothing in common;
- letter by letter (the words joined, spaces dropped; difflib's ratio ``2·matches / total``), which
  forgives a recogniser's mis-segmented spellings of rare words ("RSC MP" for "RCMP", "people
  mania" for "Beatlemania") that cost whole words.

The nearest sentence is the one with the best letter similarity (then word score). It is in the
set when its word score reaches ``threshold`` (0.6) or its letter similarity ``char_threshold``
(0.7); the match score is the larger of the two. On the RoboCup harness (Whisper tiny.en, steered
segments) letters took the questions matched from 38 to 54 of 60, while of the 50 questions'
answers and 7 other sentences one (an answer repeating its question's words) reached 0.7.

:meth:`SentenceMatcher.vocabulary` gives the set's rare words, which the whisper backend passes
as its initial prompt so that names it would otherwise misspell ("CAPTCHA", "Beatlemania") are
spelled as in the set.
"""
from __future__ import annotations

import difflib
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

ONES = ["zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten", "eleven", "twelve",
        "thirteen", "fourteen", "fifteen", "sixteen", "seventeen", "eighteen", "nineteen"]
TENS = ["", "", "twenty", "thirty", "forty", "fifty", "sixty", "seventy", "eighty", "ninety"]
ABBREVIATIONS = {"mr": "mister", "mrs": "missus", "dr": "doctor", "st": "saint", "vs": "versus", "&": "and",
                 "%": "percent", "what's": "what is", "who's": "who is", "where's": "where is", "how's": "how is",
                 "it's": "it is", "that's": "that is", "there's": "there is", "when's": "when is"}
ORDINALS = {"one": "first", "two": "second", "three": "third", "five": "fifth", "eight": "eighth", "nine": "ninth",
            "twelve": "twelfth"}  # the rest: -y to -ieth, else + th
MAX_SENTENCES = 10_000  # each transcript is compared with every sentence: ~70 µs each here


class GrammarError(ValueError):
    """A grammar that cannot be expanded into a finite list of sentences."""


def number_words(n: int) -> str:
    """0..999,999 in words, years as spoken ("1915": "nineteen fifteen")."""
    if n < 20:
        return ONES[n]
    if n < 100:
        return TENS[n // 10] + ("" if n % 10 == 0 else " " + ONES[n % 10])
    if 1100 <= n <= 2099 and n % 100 and not 2000 <= n <= 2009:  # a year: "nineteen fifteen"
        return number_words(n // 100) + " " + (number_words(n % 100) if n % 100 >= 10 else "oh " + ONES[n % 100])
    if n < 1000:
        return ONES[n // 100] + " hundred" + ("" if n % 100 == 0 else " " + number_words(n % 100))
    return number_words(n // 1000) + " thousand" + ("" if n % 1000 == 0 else " " + number_words(n % 1000))


def ordinal_words(n: int) -> str:
    """An ordinal in words, its last word turned: 20 "twentieth", 21 "twenty first", 100 "one hundredth"."""
    *head, last = number_words(n).split()
    last = ORDINALS.get(last) or (last[:-1] + "ieth" if last.endswith("y") else last + "th")
    return " ".join([*head, last])


def normalise(text: str) -> list[str]:
    """The words of ``text`` as they are compared."""
    text = text.lower().replace("’", "'")
    text = re.sub(r"\b(?:[a-z]\.){2,}", lambda m: m.group(0).replace(".", "") + " ", text)  # r.c.m.p. -> rcmp
    text = re.sub(r"(\d),(\d{3})", r"\1\2", text)  # 1,000 -> 1000
    text = re.sub(r"(?<!\d)(\d{1,6})(?:st|nd|rd|th)\b", lambda m: " " + ordinal_words(int(m.group(1))) + " ", text)
    text = re.sub(r"\d+", lambda m: " " + number_words(int(m.group(0))) + " " if len(m.group(0)) <= 6
                  else m.group(0), text)
    words: list[str] = []
    for word in re.split(r"[^a-z0-9'&%]+", text):
        word = word.strip("'")
        if word:
            words.extend(ABBREVIATIONS.get(word, word).split())
    return words


def word_distance(a: list[str], b: list[str]) -> int:
    """Levenshtein distance in words."""
    previous = list(range(len(b) + 1))
    for i, word in enumerate(a, 1):
        current = [i]
        for j, other in enumerate(b, 1):
            current.append(min(previous[j] + 1, current[j - 1] + 1, previous[j - 1] + (word != other)))
        previous = current
    return previous[-1]


@dataclass(frozen=True)
class Match:
    sentence: str  # the allowed sentence nearest the transcript ("" if there are none)
    score: float  # 1 - word distance / the longer one's length
    in_set: bool  # score >= the threshold


def chosen_first(matches: list[Match]) -> list[int]:
    """The order in which a segment's hypotheses are reported, given each one's match: the
    hypothesis whose match is in the set with the best score first (ties: the higher ranked), then
    the others in their own order. None in the set: their own order (the first is out of set)."""
    in_set = [i for i, m in enumerate(matches) if m.in_set]
    if not in_set:
        return list(range(len(matches)))
    best = max(in_set, key=lambda i: (matches[i].score, -i))
    return [best, *(i for i in range(len(matches)) if i != best)]


class SentenceMatcher:
    def __init__(self, sentences: list[str], threshold: float = 0.6, char_threshold: float = 0.7) -> None:
        if not sentences:
            raise GrammarError("no allowed sentences")
        self.sentences = list(dict.fromkeys(s.strip() for s in sentences if s.strip()))
        if len(self.sentences) > MAX_SENTENCES:
            raise GrammarError(f"{len(self.sentences)} sentences, more than the {MAX_SENTENCES} a closed set holds "
                               "(each transcript is compared with every one)")
        self._normalised = [normalise(s) for s in self.sentences]
        self._letters = ["".join(words) for words in self._normalised]
        self.threshold, self.char_threshold = threshold, char_threshold

    def match(self, transcript: str) -> Match:
        keys = self._keys(transcript)
        best = max(range(len(keys)), key=lambda i: (keys[i], -i))
        char_score, word_score = keys[best]
        in_set = word_score >= self.threshold or char_score >= self.char_threshold
        return Match(self.sentences[best], round(max(char_score, word_score, 0.0), 4), in_set)

    def ranking(self, transcript: str) -> list[int]:
        """The indices of the sentences, nearest ``transcript`` first (as :meth:`match` ranks them)."""
        keys = self._keys(transcript)
        return sorted(range(len(keys)), key=lambda i: (-keys[i][0], -keys[i][1], i))

    def _keys(self, transcript: str) -> list[tuple[float, float]]:
        """Each sentence's (letter similarity, word score) to ``transcript``."""
        words = normalise(transcript)
        letters = "".join(words)
        keys = []
        for allowed, allowed_letters in zip(self._normalised, self._letters, strict=True):
            word_score = 1.0 - word_distance(words, allowed) / (max(len(words), len(allowed)) or 1)
            keys.append((difflib.SequenceMatcher(None, letters, allowed_letters, autojunk=False).ratio() if letters
                         else 0.0, word_score))
        return keys

    def vocabulary(self, max_words: int = 95) -> list[str]:
        """The set's rare words (in at most two sentences, four letters or more), the rarest and
        longest first: at most ``max_words`` (95 of the RoboCup set fit Whisper's prompt of 223 tokens)."""
        counts = Counter(word for words in self._normalised for word in set(words))
        rare = [w for w, n in sorted(counts.items(), key=lambda wn: (wn[1], -len(wn[0]), wn[0]))
                if n <= 2 and len(w) >= 4]
        return rare[:max_words]

    @classmethod
    def from_file(cls, path: Path, threshold: float, char_threshold: float = 0.7) -> SentenceMatcher:
        text = path.read_text()
        if path.suffix == ".gram" or text.lstrip().startswith("#JSGF"):
            return cls(expand_jsgf(text), threshold, char_threshold)
        return cls([line for line in text.splitlines() if line.strip() and not line.startswith("#")], threshold,
                   char_threshold)


def expand_jsgf(text: str) -> list[str]:
    """Every sentence of a finite JSGF grammar's public rules: alternatives ``|``, sequences,
    groups ``( )``, optionals ``[ ]`` and rule references ``<name>``. Weights, tags and
    repetition (``*``, ``+``, which make it infinite) are refused."""
    rules, public = jsgf_rules(text)
    sentences: list[str] = []
    for name in public:
        sentences.extend(" ".join(words) for words in _expand_rule(name, rules, ()))
    return list(dict.fromkeys(sentences))


def jsgf_rules(text: str) -> tuple[dict[str, str], list[str]]:
    """A JSGF grammar's rules (name -> body, comments left out) and its public rules' names."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    rules: dict[str, str] = {}
    public: list[str] = []
    for match in re.finditer(r"(public\s+)?<([\w.$-]+)>\s*=\s*(.*?);", text, re.S):
        rules[match.group(2)] = match.group(3)
        if match.group(1):
            public.append(match.group(2))
    if not public:
        raise GrammarError("the grammar has no public rule")
    return rules, public


def jsgf_tokens(body: str) -> list[str]:
    """A rule body's tokens: rule references, ``( ) [ ] | * +``, tags, weights and words."""
    return re.findall(r"<[\w.$-]+>|[()\[\]|*+]|\{[^}]*\}|/[^/]*/|[^\s()\[\]|<>*+{}/]+", body)


def _expand_rule(name: str, rules: dict[str, str], seen: tuple[str, ...]) -> list[list[str]]:
    if name in seen:
        raise GrammarError(f"rule <{name}> refers to itself: its sentences are not finite")
    if name not in rules:
        raise GrammarError(f"rule <{name}> is not defined")
    tokens = jsgf_tokens(rules[name])
    expanded, end = _alternatives(tokens, 0, rules, (*seen, name))
    if end != len(tokens):
        raise GrammarError(f"rule <{name}>: unexpected {tokens[end]!r}")
    return expanded


def _alternatives(tokens: list[str], i: int, rules, seen) -> tuple[list[list[str]], int]:
    options, i = _sequence(tokens, i, rules, seen)
    while i < len(tokens) and tokens[i] == "|":
        more, i = _sequence(tokens, i + 1, rules, seen)
        options += more
    return options, i


def _sequence(tokens: list[str], i: int, rules, seen) -> tuple[list[list[str]], int]:
    result: list[list[str]] = [[]]
    while i < len(tokens) and tokens[i] not in ("|", ")", "]"):
        token = tokens[i]
        if token in ("*", "+") or token.startswith("{") or token.startswith("/"):
            raise GrammarError(f"{token!r} (repetition, tags or weights) is not supported in closed-set matching")
        if token in ("(", "["):
            inner, i = _alternatives(tokens, i + 1, rules, seen)
            if i >= len(tokens) or tokens[i] != {"(": ")", "[": "]"}[token]:
                raise GrammarError(f"unbalanced {token!r}")
            if token == "[":
                inner = [*inner, []]
        elif token.startswith("<"):
            inner = [[]] if token in ("<NULL>",) else _expand_rule(token[1:-1], rules, seen)
        else:
            inner = [[token]]
        result = [left + right for left in result for right in inner]
        if len(result) > MAX_SENTENCES:
            raise GrammarError(f"more than {MAX_SENTENCES} sentences")
        i += 1
    return result, i

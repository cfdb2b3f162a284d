"""What the robot itself said: its player's ``playback`` results, and whether an utterance is its own voice.

A player reports each part of an item it plays that sounds as a ``playback`` result spanning the capture
time it is to play, and again with its real end if it was stopped early (``attributes.stopped``); the
later result of a part (its ``instance``, ``attributes.item`` and ``attributes.part``) revises the
earlier. Pure: no I/O.

The rule for the robot's own voice (residual echo the canceller left, recognised as speech), on a fused
result of a stream whose robot played during its span (docs/protocol.md, "Fused results"):

- ``playback_overlap``: the share of the anchor's span that overlaps what the robot played (0..1);
- the utterance is the robot's (``source: "robot"``) when ``playback_overlap >= ROBOT_OVERLAP`` and the
  evidence there is does not speak for a person:

  - the echo canceller's ``echo`` events in the span (esiaf_services/aec/evidence.py, :func:`person_above_echo`)
    show a converged canceller that took the echo off and left a voice standing ``PERSON_ABOVE_FLOOR_DB``
    above its output's floor: the robot's voice is 25-40 dB down there, and what stands out is someone
    else (a question the recogniser could not decode over the robot, or heard with some of the robot's
    words in it, is a person's, with its direction). A block with ``PERSON_MAX_CANCELLED_DB`` or more
    taken off counts neither way: that is the robot's residual at the canceller's ERLE, which the fast
    start's lower floor lets stand 16-23 dB above it (aec/tests/test_evidence.py's scene: 22-24 dB taken
    off; a person 10 dB below the echo had 0-20 there). Measured in bench/robot_speaks.py's rooms
    (2026-11-28, the fast start, the bound at 20 dB), it held for 16 of the 17 question segments half
    in the robot's playback (the other, 0.8 s of a question 9 s in with nothing recognised, stood at most
    14 dB above the floor; with the slow start the vad had made no segment there), and the bound changed
    the verdict of no segment of either start; the robot's own utterances in 300 s of its talk:
    esiaf_services/aec/README.md, "A fast start";
  - words were recognised (a hypothesis that is not empty) and the robot's words are known (a ``say:``
    item, or a transcript): the heard words must be at least ``ROBOT_TEXT_SIMILARITY`` the robot's, in
    its order (:func:`text_similarity`); a person who talks over the robot says other words;
  - words were recognised and the robot's are not known (a sound file played without a transcript):
    nothing tells them from the robot's, and the words are taken for a person's (a question is not
    lost; the robot's echo recognised as words is shown, so give the robot's words);
  - nothing was recognised (no asr in the fusion, or an empty hypothesis; with the orchestrator's
    ``robot_out_of_set_is_nothing``, off by default, also one out of a closed set: the words a grammar's
    recogniser forces onto the sound, its ``raw_text``, are then not taken for words heard): the overlap
    decides. With the vad's gain on (``vad.silero.level_max_gain_db``) the room's babble under the robot's
    talk is decoded so ("what is a chatbot"), and its raw words, not the robot's, made a person of it
    (docs/benchmarks.md, "Out-of-set words are no person");
  - and where the localiser marks the robot's loudspeaker (ssl's ``self_azimuth_deg``: directions with
    ``source_id`` ``self``) and places the talker on another track that is not background, that is a
    person too.
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from esiaf.results import ECHO, PLAYBACK, SPEECH_START

from .aggregate import overlap_ns

__all__ = ["ECHO", "PLAYBACK", "SELF", "SPEECH_START", "Played", "is_robot", "overlap_share", "played", "playing_at"]
ROBOT_OVERLAP = 0.5
ROBOT_TEXT_SIMILARITY = 0.5
# a person's evidence in the canceller's echo events (person_above_echo): blocks this far above the output's floor
# (people measured 16-28 dB, the robot's converged residual 10), this many of them, with this much taken off
PERSON_ABOVE_FLOOR_DB = 15.0
PERSON_MIN_BLOCKS = 2
PERSON_CANCELLED_DB = 6.0
# ... and less than this: a block the canceller took 20 dB or more off is the robot's residual at the canceller's
# ERLE, however far above a converged output's floor it stands (a person 10 dB below the echo is not 20 dB down)
PERSON_MAX_CANCELLED_DB = 20.0
SAY_PREFIX = "say: "  # a player's name for a sentence it says
SELF = "self"  # the ssl service's source id of the robot's own loudspeaker (its self_azimuth_deg setting)


@dataclass(frozen=True)
class Played:
    """One item the robot played (its latest report)."""

    key: tuple[str, int, int]  # the player instance, its item number, the part
    name: str
    start_ns: int
    end_ns: int
    stopped: bool

    @property
    def text(self) -> str:
        """What the robot said, if the item is a sentence."""
        return self.name[len(SAY_PREFIX):] if self.name.startswith(SAY_PREFIX) else ""


def played(results: Iterable[dict[str, Any]]) -> list[Played]:
    """The items that ``playback`` results (their JSON) report, each by its latest report, by start."""
    latest: dict[tuple[str, int, int], tuple[int, Played]] = {}
    for result in results:
        payload = result.get(PLAYBACK) or {}
        attributes = payload.get("attributes") or {}
        try:
            key = (str(result.get("instance", "")), int(attributes.get("item", 0)), int(attributes.get("part", 0)))
        except (TypeError, ValueError):
            continue
        item = Played(key=key, name=str(payload.get("text", "")), start_ns=result["span"]["start_ns"],
                      end_ns=result["span"]["end_ns"], stopped=bool(attributes.get("stopped", False)))
        order = int(result.get("sequence", 0))
        if key not in latest or order >= latest[key][0]:
            latest[key] = (order, item)
    return sorted((item for _, item in latest.values()), key=lambda p: (p.start_ns, p.key))


def overlap_share(items: Iterable[Played], start_ns: int, end_ns: int) -> float:
    """The share of [start_ns, end_ns] that any of ``items`` covers (their union), 0..1."""
    length = end_ns - start_ns
    if length <= 0:
        return float(any(p.start_ns <= start_ns <= p.end_ns for p in items))
    covered, reach = 0, start_ns
    for item in sorted(items, key=lambda p: p.start_ns):
        lo, hi = max(item.start_ns, reach), min(item.end_ns, end_ns)
        if hi > lo:
            covered += overlap_ns(lo, hi, start_ns, end_ns)
            reach = hi
    return min(1.0, covered / length)


def playing_at(items: Iterable[Played], capture_ns: int) -> Played | None:
    """The item playing at ``capture_ns``, if any."""
    return next((p for p in items if p.start_ns <= capture_ns < p.end_ns), None)


def _words(text: str) -> list[str]:
    return re.findall(r"[\w']+", text.lower())


def text_similarity(heard: str, said: str) -> float:
    """The share of the heard words that the robot said in that order: their longest common subsequence
    over the heard words (0..1; 0 when nothing was heard). Words in common alone ("is", "the") are not
    enough: "where is the bathroom" against "the kitchen is on your left" is 0.25, not 0.5."""
    heard_words, said_words = _words(heard), _words(said)
    if not heard_words:
        return 0.0
    row = [0] * (len(said_words) + 1)
    for word in heard_words:
        diagonal = 0
        for j, other in enumerate(said_words, 1):
            diagonal, row[j] = row[j], diagonal + 1 if word == other else max(row[j], row[j - 1])
    return row[-1] / len(heard_words)


def _heard_text(results: dict[str, list[dict[str, Any]]], anchor: dict[str, Any],
                out_of_set_is_nothing: bool = False) -> str | None:
    """The best hypothesis's words of the utterance (the anchor's, or its speech results'), or None where
    nothing was recognised (no hypothesis, an empty one, or with ``out_of_set_is_nothing`` one out of a
    closed set)."""
    for result in [anchor, *results.get("speech", [])]:
        hypotheses = (result.get("speech") or {}).get("hypotheses") or []
        if hypotheses:
            best = hypotheses[0]
            if out_of_set_is_nothing and best.get("out_of_set"):  # what a closed set's recogniser forced onto
                return None  # the sound (raw_text) is no words heard, from babble as from the robot's echo
            return str(best.get("raw_text") or best.get("text") or "") or None
    return None


def person_above_echo(echoes: Iterable[dict[str, Any]]) -> bool:
    """Whether the canceller's ``echo`` events (their JSON) of a span say someone other than the robot speaks:
    all from a converged canceller; of its blocks standing ``PERSON_ABOVE_FLOOR_DB`` above the output's floor,
    at least ``PERSON_MIN_BLOCKS`` and most of them had the echo taken off (``PERSON_CANCELLED_DB``). A loud
    block the canceller barely changed is no evidence: the robot's voice passed it (it lost the echo for a
    moment), or there was no echo."""
    loud = cancelled = 0
    for event in echoes:
        attributes = (event.get(ECHO) or {}).get("attributes") or {}
        if not isinstance(attributes, dict) or attributes.get("converged") is not True:
            return False  # the robot's echo passes a canceller that has not converged: no evidence
        if _decibels(attributes.get("above_floor_db")) >= PERSON_ABOVE_FLOOR_DB:
            taken_off = _decibels(attributes.get("cancelled_db"))
            if taken_off >= PERSON_MAX_CANCELLED_DB:
                continue  # the robot's residual standing out of a low floor: neither a person nor a lost echo
            loud += 1
            cancelled += taken_off >= PERSON_CANCELLED_DB
    return cancelled >= PERSON_MIN_BLOCKS and 2 * cancelled > loud


def _decibels(value: Any) -> float:
    """An echo event's figure, or -inf (no evidence) where a peer sent none, or not a finite number."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return float("-inf")


def is_robot(share: float, items: list[Played], anchor: dict[str, Any],
             results: dict[str, list[dict[str, Any]]], ssl: dict[str, Any] | None = None,
             echoes: Iterable[dict[str, Any]] = (), out_of_set_is_nothing: bool = False) -> bool:
    """The module's rule: the utterance is the robot's own voice. ``ssl``: the fused result's ssl aggregate;
    ``echoes``: the echo canceller's ``echo`` events (JSON) overlapping the utterance; ``out_of_set_is_nothing``:
    the orchestrator's ``robot_out_of_set_is_nothing``."""
    if share < ROBOT_OVERLAP or person_above_echo(echoes):
        return False
    said = " ".join(p.text for p in items if p.text)
    heard = _heard_text(results, anchor, out_of_set_is_nothing)
    if heard is not None and (not said or text_similarity(heard, said) < ROBOT_TEXT_SIMILARITY):
        return False
    # the localiser marks the robot's loudspeaker (self) and placed the talker elsewhere: a person
    marks_self = any(d.get("source_id") == SELF for r in results.get("ssl", [])
                     for d in (r.get("ssl") or {}).get("directions", []))
    return not (marks_self and ssl is not None and ssl.get("source_id") != SELF and not ssl.get("background"))

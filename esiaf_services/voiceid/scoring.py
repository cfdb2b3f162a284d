"""Open-set speaker identification by cosine scoring, and anonymous voices per stream.

A voice's score is the mean of its ``top_k`` best cosine similarities between the segment's
embedding and that voice's embeddings (``top_k=1`` is the maximum). With ``mean_weight`` w > 0 and
learnt embeddings told apart from enrolled ones, it is ``(1 - w)`` × the top-k score over the
*enrolled* embeddings alone plus ``w`` × the cosine to the normalised mean of *all* its embeddings,
enrolled and learnt: learning moves the mean but adds no chance of a high similarity, so a voice
that learnt does not pull other speakers' utterances to itself as the top-k over all does. The best voice
wins if its score reaches ``threshold`` (calibrated on EmoDB by ``bench/voiceid.py``: the
equal-error-rate point of the open-set trial); otherwise the segment is unknown and goes to
:class:`AnonymousVoices`. The reported probability maps the score through a logistic around
the threshold (0.5 at the threshold; ``SLOPE`` per unit cosine).
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

SLOPE = 40.0  # logistic slope per unit of cosine: ±0.05 around the threshold is 0.12 … 0.88


def probability(score: float, threshold: float) -> float:
    return 1.0 / (1.0 + math.exp(-SLOPE * (score - threshold)))


@dataclass(frozen=True)
class Match:
    label: str  # a voice's name, or "" for unknown
    score: float
    probability: float
    scores: dict[str, float]  # every enrolled voice's score


class VoiceBook:
    """Enrolled voices: name → (n, size) unit embeddings, and ``learnt``: name → the (m, size) learnt
    ones (scored as enrolled ones with ``mean_weight`` 0, else through the mean only; see above).

    With a ``cohort`` (unit embeddings of other speakers, none of them enrolled) the scores are
    adaptive s-norm: the raw score ``s`` minus the mean, over the standard deviation, of the
    ``cohort_top`` best scores of the voice against the cohort (``z``) and of the segment against
    the cohort (``t``), averaged: ``((s - μv) / σv + (s - μt) / σt) / 2``. The threshold is then
    in those units, not in cosine.
    """

    def __init__(self, voices: dict[str, np.ndarray] | None = None, top_k: int = 3,
                 cohort: np.ndarray | None = None, cohort_top: int = 20,
                 learnt: dict[str, np.ndarray] | None = None, mean_weight: float = 0.0):
        self.voices = {name: _unit(np.atleast_2d(np.asarray(e, np.float32))) for name, e in (voices or {}).items()}
        self.learnt = {name: _unit(np.atleast_2d(np.asarray(e, np.float32))) for name, e in (learnt or {}).items()
                       if np.size(e) and name in self.voices}
        self.top_k, self.mean_weight = top_k, mean_weight
        self.means = {name: _unit(np.mean(np.concatenate([enrolled] + ([self.learnt[name]] if name in self.learnt
                                                                         else [])), axis=0))
                      for name, enrolled in self.voices.items()}
        self.cohort = None if cohort is None else _unit(np.atleast_2d(np.asarray(cohort, np.float32)))
        self.cohort_top = cohort_top
        self.voice_stats = {} if self.cohort is None else {
            name: _top_stats(self._voice_scores(name, self.cohort.T), cohort_top) for name in self.voices}

    def _voice_scores(self, name: str, probes: np.ndarray) -> np.ndarray:
        """The voice's score against each column of ``probes``."""
        enrolled = self.voices[name]
        if self.mean_weight <= 0:  # top-k over every embedding, enrolled and learnt
            if name in self.learnt:
                enrolled = np.concatenate([enrolled, self.learnt[name]])
            return _top_mean(enrolled @ probes, self.top_k)
        return ((1 - self.mean_weight) * _top_mean(enrolled @ probes, self.top_k)
                + self.mean_weight * (self.means[name] @ probes))

    def raw_scores(self, embedding: np.ndarray) -> dict[str, float]:
        return {name: float(self._voice_scores(name, embedding[:, None])[0]) for name in self.voices}

    def scores(self, embedding: np.ndarray) -> dict[str, float]:
        raw = self.raw_scores(embedding)
        if self.cohort is None:
            return raw
        mean_t, std_t = _top_stats(self.cohort @ embedding, self.cohort_top)
        return {name: 0.5 * ((s - self.voice_stats[name][0]) / self.voice_stats[name][1] + (s - mean_t) / std_t)
                for name, s in raw.items()}

    def identify(self, embedding: np.ndarray, threshold: float) -> Match:
        scores = self.scores(embedding)
        if not scores:
            return Match("", 0.0, 0.0, {})
        best = max(scores, key=scores.__getitem__)
        p = probability(scores[best], threshold)
        return Match(best if scores[best] >= threshold else "", scores[best], p, scores)


@dataclass(frozen=True)
class LearningRule:
    """When an identified utterance is confident enough to be learnt by its voice: its score is at
    least ``margin`` above the threshold and ``margin`` above the next voice's score (with a single
    voice enrolled, the threshold alone)."""

    threshold: float
    margin: float

    def learns(self, scores: dict[str, float]) -> bool:
        if not scores:
            return False
        ranked = sorted(scores.values(), reverse=True)
        next_best = ranked[1] if len(ranked) > 1 else -math.inf
        return ranked[0] >= self.threshold + self.margin and ranked[0] - next_best >= self.margin


class AnonymousVoices:
    """Unknown voices of one stream: ``voice-1``, ``voice-2``, … kept by running mean embedding.

    At most ``limit`` voices are remembered; the one heard least recently is forgotten first.
    """

    def __init__(self, threshold: float, limit: int = 16):
        self.threshold, self.limit = threshold, limit
        self.voices: OrderedDict[str, np.ndarray] = OrderedDict()  # id → sum of embeddings
        self.counter = 0

    def assign(self, embedding: np.ndarray) -> tuple[str, float]:
        """The id of this unknown voice (new or heard before) and its similarity to it."""
        best, best_score = "", -1.0
        for voice_id, total in self.voices.items():
            score = float(_unit(total) @ embedding)
            if score > best_score:
                best, best_score = voice_id, score
        if best and best_score >= self.threshold:
            self.voices[best] = self.voices[best] + embedding
            self.voices.move_to_end(best)
            return best, best_score
        self.counter += 1
        voice_id = f"voice-{self.counter}"
        self.voices[voice_id] = embedding.astype(np.float32)
        while len(self.voices) > self.limit:
            self.voices.popitem(last=False)
        return voice_id, 1.0


def _top_mean(similarities: np.ndarray, top: int) -> np.ndarray:
    """Per column, the mean of its ``top`` highest rows."""
    return np.mean(-np.sort(-similarities, axis=0)[:top], axis=0)


def _top_stats(scores: np.ndarray, top: int) -> tuple[float, float]:
    """Mean and standard deviation (at least 1e-3) of the ``top`` highest scores."""
    best = np.sort(np.asarray(scores, np.float64))[::-1][:top]
    return float(np.mean(best)), max(float(np.std(best)), 1e-3)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)

"""Closed-set decoding by Whisper's acoustic model: which allowed sentence the audio supports best.

Transcribe-then-match (``matching.py``) picks the sentence nearest the transcript's *text*; this
picks the sentence the *audio* supports best, by the model's own probability of its tokens:

1. The segment is encoded once, over its own length plus ``PAD_S`` (1 s) of silence (Whisper's 30 s
   window costs ~0.9 CPU-s to encode on this machine, a 3 s question plus the pad ~0.04; the pad
   lets the decoder see the speech end, without it greedy decoding repeats the sentence; 2 s before
   2026-11-28, the same accuracy for ~10 % more CPU).
2. A free decode of that encoding (beam ``beam_size``, ``n_best`` hypotheses, no timestamps) gives
   the raw transcript and its n-best. By default greedy (beam 1, one hypothesis): the shortlist
   it gives recognised as many questions as the three of beam 3 (or of the asr's former beam 5),
   for 17-28 % less of the utterance's CPU (bench/closed_set.py ``--before``; docs/benchmarks.md).
3. Shortlist: the ``shortlist`` sentences nearest those hypotheses by text (letters, as
   ``matching.py`` compares them), taken in turn from each hypothesis's ranking, best hypothesis
   first. Text distance costs microseconds per sentence; scoring one costs ~25 ms (one batch item
   of CTranslate2's ``Whisper.align``), so scoring all 50 RoboCup questions cost ~1.5 CPU-s.
4. Each shortlisted sentence, and the free transcript, is force-decoded
   (``Whisper.align`` from the same encoder output): its score is the sum of the log-probabilities
   of its tokens and of the end of text, given the audio and the prompt. The best wins.
5. Rejection: the free transcript is the model's own best guess, so its score is the reference.
   The best sentence is out of set when it falls more than ``reject_per_token`` nats per token
   (of the longer of the two) below it. A sentence that normalises to the free transcript is in
   the set whatever its score. (Calibration: bench/closed_set.py and the README.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from esiaf_services.asr.matching import SentenceMatcher, normalise
from esiaf_services.asr.recognizer import Word

MIN_SAMPLES = 1600  # 0.1 s at 16 kHz: shorter is not decoded, as whisper.py
PAD_S = 1.0  # silence after the segment in the encoder's input (docstring, step 1)
MAX_TOKENS_PER_S = 6  # a free decode longer than this many tokens per second of audio is a loop
LOGPROB_FLOOR = 1e-30
MIN_PER_TOKEN = -4.0  # rejection: the best sentence's log-probability per token below this: out of set ...
MAX_BELOW_RAW = math.inf  # ... or more than this per token below the free transcript (off: docstring, step 5)


@dataclass(frozen=True)
class Scored:
    sentence: str
    logprob: float  # log-probability of its tokens and the end of text, given the audio (nats)
    tokens: int


@dataclass
class ClosedSetResult:
    raw_text: str  # the free decode's best transcript ("" when it heard nothing)
    raw_logprob: float  # its score, as the sentences'
    raw_tokens: int
    ranked: list[Scored]  # the shortlist, best first
    in_set: bool
    words: list[Word] = field(default_factory=list)  # the chosen sentence's words, timed by the alignment
    no_speech_prob: float = 0.0

    @property
    def margin(self) -> float:
        """The best sentence's lead over the runner-up, in nats (inf with one candidate)."""
        return self.ranked[0].logprob - self.ranked[1].logprob if len(self.ranked) > 1 else math.inf

    def posteriors(self) -> list[float]:
        """Each shortlisted sentence's probability among the shortlist (a softmax of the scores)."""
        scores = np.array([s.logprob for s in self.ranked])
        weights = np.exp(scores - scores.max())
        return [float(w) for w in weights / weights.sum()]

    @property
    def per_token(self) -> float:
        """The best sentence's log-probability per token."""
        return self.ranked[0].logprob / max(1, self.ranked[0].tokens)

    @property
    def below_raw(self) -> float:
        """How far the best sentence scores below the free transcript, per token (of the longer)."""
        if not self.raw_text:
            return 0.0
        return (self.raw_logprob - self.ranked[0].logprob) / max(1, self.ranked[0].tokens, self.raw_tokens)


class ClosedSetDecoder:
    """Decodes a segment into one of ``matcher``'s sentences (or out of set) with ``model``, a
    faster-whisper ``WhisperModel``."""

    def __init__(self, model, matcher: SentenceMatcher, shortlist: int = 6,
                 beam_size: int = 1, n_best: int = 1, min_per_token: float = MIN_PER_TOKEN,
                 max_below_raw: float = MAX_BELOW_RAW, pad_s: float = PAD_S) -> None:
        from faster_whisper.tokenizer import Tokenizer
        from faster_whisper.transcribe import get_suppressed_tokens

        self.model, self.matcher = model, matcher
        self.shortlist, self.beam_size, self.n_best = max(1, shortlist), beam_size, max(1, n_best)
        self.min_per_token, self.max_below_raw, self.pad_s = min_per_token, max_below_raw, pad_s
        self.tokenizer = Tokenizer(model.hf_tokenizer, model.model.is_multilingual, task="transcribe", language="en")
        self.start = model.get_prompt(self.tokenizer, [], without_timestamps=True)
        self.suppress = list(get_suppressed_tokens(self.tokenizer, [-1]))
        self._spellings: dict[int, list[list[int]]] = {}  # a sentence's tokens, made when first shortlisted

    def encode(self, samples: np.ndarray):
        """The encoder output of ``samples`` (float32, 16 kHz) and the number of its frames of audio."""
        import ctranslate2
        features = self.model.feature_extractor(samples.astype(np.float32, copy=False))[:, :-1]
        frames = features.shape[-1]
        wanted = min(3000, frames + round(self.pad_s * 100))
        wanted += wanted % 2  # the encoder halves it
        features = np.pad(features, ((0, 0), (0, max(0, wanted - frames))))[:, :wanted]
        encoded = self.model.model.encode(ctranslate2.StorageView.from_array(
            np.ascontiguousarray(features[None], dtype=np.float32)))
        return encoded, min(frames, wanted)

    def decode(self, samples: np.ndarray) -> ClosedSetResult | None:
        """The segment's sentence (float32 samples at 16 kHz), or None when it is too short to decode."""
        if samples.size < MIN_SAMPLES:
            return None
        encoded, frames = self.encode(samples)
        most = min(self.model.max_length, len(self.start) + round(MAX_TOKENS_PER_S * frames / 100) + 4)
        result = self.model.model.generate(
            encoded, [self.start], beam_size=max(self.beam_size, self.n_best), num_hypotheses=self.n_best,
            return_scores=True, return_no_speech_prob=True, max_length=most, suppress_blank=True,
            suppress_tokens=self.suppress)[0]
        heard = [once(self.tokenizer.decode(ids).strip()) for ids in result.sequences_ids]
        heard = [text for text in heard if normalise(text)]
        candidates = self.nearest(heard)
        spellings = [self.spellings(i) for i in candidates]
        tokens = [t for each in spellings for t in each] + [self.text_tokens(t) for t in heard[:1]]
        aligned = self.align(encoded, frames, tokens)
        scores = [logprob(a.text_token_probs) for a in aligned]
        raw_logprob = scores[-1] if heard else -math.inf
        ranked, best_k, at = [], [], 0
        for index, each in zip(candidates, spellings, strict=True):  # a sentence scores as its likeliest spelling
            k = max(range(at, at + len(each)), key=lambda j: scores[j])
            ranked.append(Scored(self.matcher.sentences[index], scores[k], len(tokens[k])))
            best_k.append(k)
            at += len(each)
        order = sorted(range(len(ranked)), key=lambda i: -ranked[i].logprob)
        ranked = [ranked[i] for i in order]
        raw_tokens = len(tokens[-1]) if heard else 0
        result_ = ClosedSetResult(heard[0] if heard else "", raw_logprob, raw_tokens, ranked, False,
                                  no_speech_prob=float(result.no_speech_prob))
        same = bool(heard) and normalise(heard[0]) == normalise(ranked[0].sentence)
        result_.in_set = same or (result_.per_token >= self.min_per_token and result_.below_raw <= self.max_below_raw)
        chosen = best_k[order[0]]
        result_.words = self.words(aligned[chosen], tokens[chosen], frames)
        return result_

    def nearest(self, heard: list[str]) -> list[int]:
        """The shortlist: indices of the sentences nearest each hypothesis by text, taken in turn
        (the first hypothesis's nearest, the second's, ..., then each one's second nearest ...)."""
        if not heard:
            return list(range(min(self.shortlist, len(self.matcher.sentences))))
        rankings = [self.matcher.ranking(text)[:self.shortlist] for text in heard]
        chosen: list[int] = []
        for depth in range(self.shortlist):
            for ranking in rankings:
                if depth < len(ranking) and ranking[depth] not in chosen:
                    chosen.append(ranking[depth])
                    if len(chosen) == self.shortlist:
                        return chosen
        return chosen

    def spellings(self, index: int) -> list[list[int]]:
        """The tokens of sentence ``index`` as written and, if different, in lower case after its first
        letter (Whisper finds "When was the Mounted Police formed?" far likelier than "... The ...")."""
        if index not in self._spellings:
            sentence = self.matcher.sentences[index]
            lower = sentence[:1] + sentence[1:].lower()
            self._spellings[index] = [self.text_tokens(text) for text in dict.fromkeys((sentence, lower))]
        return self._spellings[index]

    def text_tokens(self, text: str) -> list[int]:
        return self.tokenizer.encode(" " + text.strip())

    def align(self, encoded, frames: int, tokens: list[list[int]]) -> list:
        """CTranslate2's forced alignment of each token list to the one encoder output (repeated
        along the batch, as ``align`` wants one encoder output per sequence)."""
        import ctranslate2
        if len(tokens) > 1:
            array = np.array(encoded)
            encoded = ctranslate2.StorageView.from_array(np.ascontiguousarray(np.repeat(array, len(tokens), 0)))
        return self.model.model.align(encoded, self.start, tokens, [frames // 2] * len(tokens))

    def words(self, aligned, tokens: list[int], frames: int) -> list[Word]:
        """The words of an aligned sentence, timed as faster-whisper times them (``find_alignment``:
        a word starts where the alignment path first reaches its first token)."""
        words, word_tokens = self.tokenizer.split_to_word_tokens([*tokens, self.tokenizer.eot])
        pairs = np.array(aligned.alignments, dtype=int).reshape(-1, 2)
        if len(word_tokens) <= 1 or not len(pairs):
            return []
        boundaries = np.pad(np.cumsum([len(t) for t in word_tokens[:-1]]), (1, 0))
        jumps = np.pad(np.diff(pairs[:, 0]), (1, 0), constant_values=1).astype(bool)
        times = pairs[:, 1][jumps] / self.model.tokens_per_second
        if len(times) <= boundaries[-1]:  # the path missed a token: no timing to trust
            return []
        probabilities = np.asarray(aligned.text_token_probs)
        end_s = frames / 100
        return [Word(word.strip(), min(float(times[first]), end_s), min(float(times[last]), end_s),
                     float(np.mean(probabilities[first:last])))
                for word, first, last in zip(words, boundaries[:-1], boundaries[1:], strict=False) if word.strip()]

def logprob(probabilities) -> float:
    return float(np.sum(np.log(np.maximum(np.asarray(probabilities, dtype=np.float64), LOGPROB_FLOOR))))


def once(text: str) -> str:
    """``text`` without the repeats of a decode caught in a loop ("What is X? What is X? What is"
    -> "What is X?"): the shortest opening of at least two words that the rest only repeats."""
    words = text.split()
    keys = [" ".join(normalise(word)) for word in words]
    for period in range(2, len(words) - 1):
        if all(keys[i] == keys[i % period] for i in range(period, len(words))):
            return " ".join(words[:period])
    return text

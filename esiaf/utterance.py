"""Utterance analysers: one result per VAD segment, over its speech span.

Subclass :class:`UtteranceComponent`, set ``service`` and ``kind``, and implement one method,
``analyse(samples, rate)``: the segment's speech (float32 mono in [-1, 1), no VAD pre-roll or
hang-over) and its sample rate. Return what it found as a dict:

- a label: ``{"label": "angry", "probability": 0.8, "class_probabilities": {...}}``;
- a number: ``{"value": 3.2}``; a text ``{"text": ...}``; anything JSON-able under ``"attributes"``;
- or ``{"nothing": "why"}``: the audio was covered and there is nothing to say about it.

The SDK collects each stream's segment separately, sends ``nothing`` for segments too short
(``min_speech_ms``) or too quiet (``silence_db``) to judge, and emits the result spanning the
segment, so fusion never waits for a result that will not come. A kind that is not built in
(emotion, gender, voice_id are) travels as a generic result and is stored, fused, aggregated
(label distribution, mean value) and shown like the built-in ones.

Analysers that need the same features of an utterance can run in one process: the ``guests``
setting names the components this one hosts (``esiaf/hosting.py``), each still its own
service to the orchestrator; features asked for through ``esiaf.features.shared`` are then
computed once per utterance for all of them.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from esiaf.audio import Audio
from esiaf.features import feature_counts
from esiaf.formats import AudioFormat
from esiaf.hosting import Host, HostSettings
from esiaf.per_stream import PerStream
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import LABEL_PAYLOADS, valid_kind
from esiaf.settings import ComponentSettings

log = logging.getLogger(__name__)
_LABEL_FIELDS = set(pb.LabelResult.DESCRIPTOR.fields_by_name)  # label, probability, classes, embedding


class UtteranceSettings(HostSettings):
    input_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    min_speech_ms: float = 500.0  # shorter segments get "nothing": too short to judge
    silence_db: float = 45.0  # segments whose peak stays below this get "nothing" (96 dB = full scale)
    # an open segment keeps at most its last this many seconds (a VAD cuts at 8 s; a peer that never ends
    # a segment must not grow the process): the earlier audio is dropped, counted and logged
    max_utterance_s: float = Field(default=30.0, gt=0)


@dataclass
class Utterance:
    start_ns: int = 0  # the capture time of its first sample kept
    chunks: list[np.ndarray] = field(default_factory=list)
    samples: int = 0
    trimmed: bool = False  # its start was dropped (max_utterance_s): logged once per utterance


class UtteranceComponent(Host):
    """Base of every utterance analyser: implement :meth:`analyse`."""

    kind: ClassVar[str] = "other"  # the kind of result it produces, e.g. "emotion" or "rate"
    Settings: ClassVar[type[ComponentSettings]] = UtteranceSettings
    settings: UtteranceSettings  # an instance of Settings: its fields, for type checkers

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.kind != "other":
            if not valid_kind(cls.kind):
                raise TypeError(f"{cls.__name__}.kind {cls.kind!r} is not a kind name (lower case, digits, _)")
            cls.designation = cls.kind

    def __init__(self, settings: UtteranceSettings):
        super().__init__(settings)
        self.add_input(settings.input_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.utterances: PerStream[Utterance] = PerStream(lambda _: Utterance(), settings.max_streams,
                                                          "open utterance", info=self.info)  # per stream
        self.utterance_stream_id = ""  # the stream of the utterance analyse() is given
        self.analysed = 0
        self.nothing = 0

    def analyse(self, samples: np.ndarray, rate: int) -> dict[str, Any]:
        """What this analyser says about one utterance (see the module's docstring)."""
        raise NotImplementedError(f"{type(self).__name__} must implement analyse(samples, rate)")

    def on_audio(self, audio: Audio) -> None:
        if not audio.payload:
            return
        utterance = self.utterances.get(audio.stream_id)
        if not utterance.chunks:
            utterance.start_ns = audio.start_ns
        chunk = audio.as_float()[:, 0].astype(np.float32)
        utterance.chunks.append(chunk)
        utterance.samples += chunk.size
        rate = self.settings.sample_rate_hz
        while utterance.samples > self.settings.max_utterance_s * rate and len(utterance.chunks) > 1:
            dropped = utterance.chunks.pop(0)
            utterance.samples -= dropped.size
            utterance.start_ns += dropped.size * 1_000_000_000 // rate
            self.info["trimmed_s"] = round(self.info.get("trimmed_s", 0.0) + dropped.size / rate, 3)
            if not utterance.trimmed:
                utterance.trimmed = True
                log.warning("stream_id=%s: a segment longer than max_utterance_s=%g; its start is dropped",
                            audio.stream_id, self.settings.max_utterance_s)

    def on_segment_end(self, audio: Audio) -> None:
        utterance = self.utterances.pop(audio.stream_id) or Utterance(audio.start_ns)
        segment = audio.meta.segment
        span = (segment.start_ns, segment.end_ns) if segment.end_ns else (utterance.start_ns, audio.end_ns)
        samples = np.concatenate(utterance.chunks) if utterance.chunks else np.zeros(0, np.float32)
        rate = self.settings.sample_rate_hz
        if segment.end_ns:  # the speech span only: no pre-roll, no hang-over
            first = max(0, (segment.start_ns - utterance.start_ns) * rate // 1_000_000_000)
            samples = samples[first:max(first, (segment.end_ns - utterance.start_ns) * rate // 1_000_000_000)]
        started = time.process_time()
        self.utterance_stream_id = audio.stream_id
        reason = self.unusable(samples)
        found = {"nothing": reason} if reason else self.analyse(samples, rate)
        if not isinstance(found, dict):
            raise TypeError(f"{type(self).__name__}.analyse must return a dict, not {type(found).__name__}")
        if "nothing" in found:
            self.nothing += 1
            self.info["nothing"] = self.nothing
            self.emit(self.kind, span, stream_id=audio.stream_id, nothing=str(found["nothing"]))
            log.info("segment stream_id=%s start_ns=%d nothing: %s", audio.stream_id, span[0], found["nothing"])
            return
        self.analysed += 1
        self.info["analysed"] = self.analysed
        if self.kind in LABEL_PAYLOADS:  # emotion, gender, voice_id: their own payload's fields
            payload = {key: value for key, value in found.items() if key in _LABEL_FIELDS}
        else:
            payload = found
        self.emit(self.kind, span, stream_id=audio.stream_id, **{self.kind: payload})
        log.info("segment stream_id=%s start_ns=%d duration_s=%.2f %s=%s cpu_ms=%.0f", audio.stream_id, span[0],
                 samples.size / rate, self.kind, found.get("label", found.get("value", "")),
                 1000 * (time.process_time() - started))

    def unusable(self, samples: np.ndarray) -> str:
        """Why this audio gets no result ("" if it can be judged)."""
        duration_ms = 1000 * samples.size / self.settings.sample_rate_hz
        if duration_ms < self.settings.min_speech_ms:
            return f"too short to judge ({duration_ms:.0f} ms < {self.settings.min_speech_ms:.0f} ms)"
        peak = float(np.max(np.abs(samples)))
        level_db = 96.0 + 20.0 * math.log10(peak) if peak > 0 else -math.inf
        if level_db < self.settings.silence_db:
            return f"silence (peak {level_db:.0f} dB < {self.settings.silence_db:.0f} dB)"
        return ""

    def stats(self) -> dict[str, Any]:
        counts = feature_counts()  # utterances whose shared features were computed, and answers reused
        if counts:
            self.info["features"] = counts
        return super().stats()

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if stream_id in self.utterances:
            self.on_segment_end(audio)  # a segment the VAD never closed
        super().on_end_of_stream(stream_id, audio)

"""Emotion service: classifies each VAD segment, as a whole, into an emotion.

:class:`UtteranceClassifier` gathers a segment's audio per stream and, when the VAD closes the
segment, asks the configured backend (``backends.py``) for a probability per label and emits a
label result spanning the segment. Audio too short or too quiet to judge is covered by a
"nothing" result over the same span, so fusion never waits for a label that will not come.
The gender service is the same component with another result type and model.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from services.emotion.backends import BackendError, Classifier, load_backend

log = logging.getLogger(__name__)


class UtteranceSettings(ComponentSettings):
    input_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    backend: str = "onnx"  # onnx | python (see backends.py)
    model: str = "emotion4"  # bundled model name, an .onnx file, or package.module:Class (python)
    model_options: dict[str, Any] = {}  # onnx: label_map, threads; python: the class's keyword arguments
    min_speech_ms: float = 500.0  # shorter segments get "nothing": too short to judge
    silence_db: float = 45.0  # segments whose peak stays below this get "nothing" (96 dB = full scale)


@dataclass
class Utterance:
    start_ns: int
    chunks: list[np.ndarray] = field(default_factory=list)


class UtteranceClassifier(Component):
    """Base of the emotion and gender services: one label result per VAD segment."""

    designation = "other"
    Settings = UtteranceSettings
    options = {"model": "bundled model name, .onnx file, or package.module:Class for the python backend",
               "backend": "onnx (default) or python"}

    def __init__(self, settings: UtteranceSettings):
        super().__init__(settings)
        self.add_input(settings.input_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.classifier: Classifier | None = None
        self.utterances: dict[str, Utterance] = {}  # open segment per stream
        self.labelled = 0
        self.nothing = 0

    def setup(self) -> None:
        s = self.settings
        try:
            self.classifier = load_backend(s.backend, s.model, s.model_options)
        except BackendError as exc:
            raise SetupError(f"{self.service} model: {exc}") from None
        if self.classifier.sample_rate_hz != s.sample_rate_hz:
            raise SetupError(f"{self.service} model {s.model} takes {self.classifier.sample_rate_hz} Hz audio, "
                             f"the service is set to {s.sample_rate_hz} Hz")
        self.info.update(model=s.model, backend=s.backend, labels=list(self.classifier.labels))
        log.info("model=%s backend=%s labels=%s", s.model, s.backend, ",".join(self.classifier.labels))

    def on_audio(self, audio: Audio) -> None:
        if not audio.payload:
            return
        utterance = self.utterances.setdefault(audio.stream_id, Utterance(audio.start_ns))
        utterance.chunks.append(audio.as_float()[:, 0].astype(np.float32))

    def on_segment_end(self, audio: Audio) -> None:
        utterance = self.utterances.pop(audio.stream_id, None) or Utterance(audio.start_ns)
        segment = audio.meta.segment
        span = (segment.start_ns, segment.end_ns) if segment.end_ns else (utterance.start_ns, audio.end_ns)
        samples = np.concatenate(utterance.chunks) if utterance.chunks else np.zeros(0, np.float32)
        if segment.end_ns:  # the speech span only, as in training (features.py): no pre-roll, no hang-over
            rate = self.settings.sample_rate_hz
            first = max(0, (segment.start_ns - utterance.start_ns) * rate // 1_000_000_000)
            samples = samples[first:max(first, (segment.end_ns - utterance.start_ns) * rate // 1_000_000_000)]
        reason = self.unusable(samples)
        if reason:
            self.nothing += 1
            self.info["nothing"] = self.nothing
            self.emit(self.designation, span, stream_id=audio.stream_id, nothing=reason)
            log.info("segment stream_id=%s start_ns=%d nothing: %s", audio.stream_id, span[0], reason)
            return
        self.label(audio.stream_id, span, samples)

    def label(self, stream_id: str, span: tuple[int, int], samples: np.ndarray) -> None:
        """Emits the label result of one usable segment (the voiceid service overrides this)."""
        started = time.process_time()
        probabilities = self.classifier.classify(samples)
        label = max(probabilities, key=probabilities.get)
        self.labelled += 1
        self.info["labelled"] = self.labelled
        self.emit(self.designation, span, stream_id=stream_id, **{self.designation: {
            "label": label, "probability": probabilities[label], "class_probabilities": probabilities}})
        log.info("segment stream_id=%s start_ns=%d duration_s=%.2f %s=%s p=%.2f cpu_ms=%.0f", stream_id,
                 span[0], samples.size / self.settings.sample_rate_hz, self.designation, label,
                 probabilities[label], 1000 * (time.process_time() - started))

    def unusable(self, samples: np.ndarray) -> str:
        """Why this audio gets no label ("" if it can be judged)."""
        duration_ms = 1000 * samples.size / self.settings.sample_rate_hz
        if duration_ms < self.settings.min_speech_ms:
            return f"too short to judge ({duration_ms:.0f} ms < {self.settings.min_speech_ms:.0f} ms)"
        peak = float(np.max(np.abs(samples)))
        level_db = 96.0 + 20.0 * math.log10(peak) if peak > 0 else -math.inf
        if level_db < self.settings.silence_db:
            return f"silence (peak {level_db:.0f} dB < {self.settings.silence_db:.0f} dB)"
        return ""

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if stream_id in self.utterances:
            self.on_segment_end(audio)  # a segment the VAD never closed
        super().on_end_of_stream(stream_id, audio)


class Emotion(UtteranceClassifier):
    """Emotion of each speech segment (neutral/angry/happy/sad; 7 EmoDB classes with model emotion7)."""

    service = "emotion"
    designation = "emotion"

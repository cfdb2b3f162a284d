"""Utterance analysers: one result per VAD segment, over its speech span.

Subclass :class:`UtteranceAnalyser`, set ``service`` and ``kind``, and implement one method,
``analyse(utterance)``: an :class:`Utterance` holds the segment's speech (``samples``, float32 mono
in [-1, 1), no VAD pre-roll or hang-over), its ``rate``, its capture span (``start_ns``, ``end_ns``)
and its ``stream_id``. Return what it found as a dict:

- a label: ``{"label": "angry", "probability": 0.8, "class_probabilities": {...}}``;
- a number: ``{"value": 3.2}``; a text ``{"text": ...}``; anything JSON-able under ``"attributes"``;
- or ``{"nothing": "why"}``: the audio was covered and there is nothing to say about it.

The SDK collects each stream's segment separately, sends ``nothing`` for segments too short
(``min_speech_ms``) or too quiet (``silence_db``) to judge, and emits the result spanning the
segment, so fusion never waits for a result that will not come. A kind that is not built in
(emotion, gender, voice_id are) travels as a generic result and is stored, fused, aggregated
(label distribution, mean value) and shown like the built-in ones. :class:`UtteranceClassifier`
is the base of analysers whose model gives a probability per label.

``analyse(samples, rate)``, the form of earlier releases, still works (it is told apart by its
signature, and logged once as deprecated); its stream is ``self.utterance_stream_id``.

Analysers that need the same features of an utterance can run in one process: the ``guests``
setting names the processors this one hosts (``esiaf/hosting.py``), each still its own
service to the orchestrator; features asked for through ``esiaf.features.shared`` are then
computed once per utterance for all of them.

An analyser that must know whether the robot was speaking (a voice identity that never learns the
robot's own voice) calls :meth:`UtteranceAnalyser.listen_to_playback` in its ``__init__``: the
player's topic becomes a second input, its chunks go to ``self.played`` (:class:`esiaf.playback.PlayedSpans`)
instead of an utterance, its end never ends a stream, and ``self.played.overlaps(stream_id, start_ns,
end_ns)`` says whether a capture span overlapped what was played.
"""
from __future__ import annotations

import inspect
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numpy as np
from pydantic import Field

from esiaf.audio import Audio
from esiaf.component import Component
from esiaf.features import feature_counts
from esiaf.formats import AudioFormat
from esiaf.hosting import HostSettings
from esiaf.per_stream import PerStream
from esiaf.playback import PlayedSpans
from esiaf.processor import Processor, SetupError
from esiaf.proto import esiaf_pb2 as pb
from esiaf.receiving import broken_off
from esiaf.results import LABEL_PAYLOADS
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


@dataclass(frozen=True)
class Utterance:
    """One VAD segment's speech, as ``analyse`` is given it."""

    samples: np.ndarray  # float32 mono in [-1, 1), the speech span only (no pre-roll, no hang-over)
    rate: int  # samples per second
    start_ns: int  # capture time of the span's start, ns since the epoch
    end_ns: int  # ... and of its end
    stream_id: str

    @property
    def duration_s(self) -> float:
        return self.samples.size / self.rate


@dataclass
class _Collecting:
    """A stream's open segment, as its chunks arrive."""
    start_ns: int = 0  # the capture time of its first sample kept
    chunks: list[np.ndarray] = field(default_factory=list)
    samples: int = 0
    trimmed: bool = False  # its start was dropped (max_utterance_s): logged once per utterance
    publisher: str = ""  # where its audio comes from, and the last sequence number taken (receiving.broken_off)
    sequence: int = 0
    end_ns: int = 0  # the capture time of its last sample


class UtteranceAnalyser(Processor):
    """Base of every utterance analyser: implement :meth:`analyse`."""

    Settings: ClassVar[type[ComponentSettings]] = UtteranceSettings
    settings: UtteranceSettings  # an instance of Settings: its fields, for type checkers
    _two_argument_analyse: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # analyse(samples, rate), the form of earlier releases: told apart by its signature
        cls._two_argument_analyse = len(inspect.signature(cls.analyse).parameters) == 3

    def __init__(self, settings: UtteranceSettings):
        super().__init__(settings)
        self.add_input(settings.input_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.utterances: PerStream[_Collecting] = PerStream(lambda _: _Collecting(), settings.max_streams,
                                                            "open utterance", info=self.info)  # per stream
        self.utterance_stream_id = ""  # the stream of the utterance analyse() is given (for analyse(samples, rate))
        self.analysed = 0
        self.nothing = 0
        self.playback_topic = ""  # listen_to_playback: the player's topic, a second input
        self.played: PlayedSpans | None = None
        if self._two_argument_analyse:
            log.warning("%s.analyse(samples, rate) is deprecated and will stop working in the next release: "
                        "write analyse(self, utterance) and read utterance.samples, utterance.rate and "
                        "utterance.stream_id", type(self).__name__)

    def analyse(self, utterance: Utterance) -> dict[str, Any]:
        """What this analyser says about one utterance (see the module's docstring)."""
        raise NotImplementedError(f"{type(self).__name__} must implement analyse(utterance)")

    def listen_to_playback(self, topic: str, tail_ms: float = 300.0, keep: int = 256) -> None:
        """Also subscribe to ``topic``, a player's (mono, at ``sample_rate_hz``): ``self.played`` keeps
        the spans it played that sound, the newest ``keep`` per stream, each with ``tail_ms`` after it."""
        self.playback_topic = topic
        self.played = PlayedSpans(keep, tail_ms, max_streams=self.settings.max_streams, info=self.info)
        self.add_input(topic, AudioFormat(self.settings.sample_rate_hz, "int16", channels=1))

    def stream_inputs(self) -> set[str]:
        """The speech's end ends a stream; the player's may never come (a robot talks on and off)."""
        return set(self.inputs) - {self.playback_topic}

    def on_audio(self, audio: Audio) -> None:
        if self.played is not None and audio.topic == self.playback_topic:
            self.played.add(audio)
            return
        if audio.stream_id in self.utterances:
            self._broken_off(audio)
        if not audio.payload:
            return
        utterance = self.utterances.get(audio.stream_id)
        if not utterance.chunks:
            utterance.start_ns = audio.start_ns
        utterance.publisher, utterance.sequence, utterance.end_ns = audio.publisher, audio.sequence, audio.end_ns
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

    def _broken_off(self, audio: Audio) -> None:
        """The stream's open segment will never end as it began (its VAD was restarted, or audio was
        lost): said nothing about, rather than analysed with the next one's audio on the next one's span."""
        utterance = self.utterances[audio.stream_id]
        why = broken_off(utterance.publisher, utterance.sequence, audio) if utterance.chunks else ""
        if why:
            self.utterances.pop(audio.stream_id)
            self._say_nothing(audio.stream_id, (utterance.start_ns, utterance.end_ns), f"utterance broken off: {why}")

    def _say_nothing(self, stream_id: str, span: tuple[int, int], why: str) -> None:
        self.nothing += 1
        self.info["nothing"] = self.nothing
        self.emit(self.kind, span, stream_id=stream_id, nothing=why)
        log.info("segment stream_id=%s start_ns=%d nothing: %s", stream_id, span[0], why)

    def on_segment_end(self, audio: Audio) -> None:
        if self.played is not None and audio.topic == self.playback_topic:
            return  # the end of a played item: no utterance
        utterance = self.utterances.pop(audio.stream_id) or _Collecting(audio.start_ns)
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
        found = {"nothing": reason} if reason else self._analyse(Utterance(samples, rate, *span, audio.stream_id))
        if not isinstance(found, dict):
            raise TypeError(f"{type(self).__name__}.analyse must return a dict, not {type(found).__name__}")
        if "nothing" in found:
            self._say_nothing(audio.stream_id, span, str(found["nothing"]))
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

    def emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None,
             **payload: Any) -> pb.Result:
        """Sends one utterance's result through the context (a handler test may put a list's append here)."""
        return self._context().emit(kind, span, stream_id=stream_id, **payload)

    def _analyse(self, utterance: Utterance) -> dict[str, Any]:
        if self._two_argument_analyse:
            return self.analyse(utterance.samples, utterance.rate)  # type: ignore[call-arg, arg-type]
        return self.analyse(utterance)

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

    def refresh_info(self) -> None:
        counts = feature_counts()  # utterances whose shared features were computed, and answers reused
        if counts:
            self.info["features"] = counts

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if stream_id in self.utterances:
            self.on_segment_end(audio)  # a segment the VAD never closed
        super().on_end_of_stream(stream_id, audio)


class UtteranceComponent(UtteranceAnalyser, Component):
    """An utterance analyser with a component's actions as its own methods (``run``, ``stop``,
    ``input_stats``...): the base of earlier releases, kept for the analysers written against it."""



class LabelModel(Protocol):
    """What a classifier's model is: its labels, its sample rate, a probability per label."""

    labels: tuple[str, ...]
    sample_rate_hz: int

    def classify(self, samples: np.ndarray) -> dict[str, float]:
        """``samples``: one utterance, mono float32 in [-1, 1] at ``sample_rate_hz``."""
        ...


class ClassifierSettings(UtteranceSettings):
    backend: str = "onnx"  # the service's name for how its model is loaded (e.g. onnx | python)
    model: str = ""  # the service's model: a bundled name, a file, or package.module:Class
    model_options: dict[str, Any] = Field(default_factory=dict)  # the backend's keyword arguments


class UtteranceClassifier(UtteranceAnalyser):
    """One label result per VAD segment, from a model: implement :meth:`load_model`."""

    Settings: ClassVar[type[ComponentSettings]] = ClassifierSettings
    settings: ClassifierSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {
        "model": "bundled model name, .onnx file, or package.module:Class for the python backend",
        "backend": "onnx (default) or python"}

    def __init__(self, settings: ClassifierSettings):
        super().__init__(settings)
        self.classifier: LabelModel | None = None

    def load_model(self) -> LabelModel:
        """The model the settings name (``backend``, ``model``, ``model_options``); SetupError if unusable."""
        raise NotImplementedError(f"{type(self).__name__} must implement load_model()")

    def setup(self) -> None:
        s = self.settings
        self.classifier = self.load_model()
        if self.classifier.sample_rate_hz != s.sample_rate_hz:
            raise SetupError(f"{self.service} model {s.model} takes {self.classifier.sample_rate_hz} Hz audio, "
                             f"the service is set to {s.sample_rate_hz} Hz")
        self.info.update(model=s.model, backend=s.backend, labels=list(self.classifier.labels))
        log.info("model=%s backend=%s labels=%s", s.model, s.backend, ",".join(self.classifier.labels))

    def analyse(self, utterance: Utterance) -> dict[str, Any]:
        if self.classifier is None:
            raise RuntimeError(f"{type(self).__name__}: analyse() before setup() loaded the model")
        probabilities = self.classifier.classify(utterance.samples)
        label = max(probabilities, key=probabilities.__getitem__)
        return {"label": label, "probability": probabilities[label], "class_probabilities": probabilities}

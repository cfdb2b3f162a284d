"""Running one analyser in-process, for its unit tests: no sockets, no orchestrator.

    from esiaf.testing import run_analyser

    results = run_analyser(SpeakingRate, "speech.wav")  # one per utterance the vad cuts
    results = run_analyser(SpeakingRate, "speech.wav", spans=[(0.5, 2.0)])  # one per span given
    assert results[0].kind == "rate" and 2 < results[0].payload["value"] < 8

The analyser runs on the same SDK code as in a pipeline (esiaf/node.py's contexts: the input side
with its conversion to the declared format, the segment collection, the "nothing" results for
audio too short or too quiet, the result messages), fed by a local node instead of ZeroMQ: the
file is played as 50 ms chunks of capture time 0 onwards, cut by the vad service's segmenter
(``vad="energy"`` or ``"silero"``), or by the spans given. Each result comes back as the analyser
emitted it (:class:`Emitted`). The process-level helpers of ESIAF's own tests (the launcher and the
orchestrator as processes) are in esiaf/tools/testing.py.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf.json_format import MessageToDict

from esiaf.formats import AudioFormat
from esiaf.links import OutputLink
from esiaf.node import Node
from esiaf.processor import Processor
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import kind_of
from esiaf.settings import ComponentSettings, load_settings
from esiaf.transport import topic_frame

CHUNK_MS = 50  # what the grabber sends by default
SOURCE_TOPIC = "grabber/audio"


@dataclass(frozen=True)
class Emitted:
    """One result as the analyser emitted it."""

    kind: str  # "emotion", "rate", ...
    start_ns: int  # its span, in capture time: 0 is the file's first sample
    end_ns: int
    stream_id: str
    payload: dict[str, Any]  # the payload's fields ({"value": 3.2}, {"label": ..., "probability": ...})
    nothing: str  # why there is no payload ("" if there is one)
    result: pb.Result  # the message itself

    @property
    def start_s(self) -> float:
        return self.start_ns / 1e9

    @property
    def end_s(self) -> float:
        return self.end_ns / 1e9


def run_analyser(analyser: type[Processor] | Processor, audio: str | Path | tuple[np.ndarray, int], *,
                 spans: Sequence[tuple[float, float]] | None = None, vad: str = "energy",
                 stream_id: str = "test", **settings: Any) -> list[Emitted]:
    """The results ``analyser`` (a class, built with its defaults and ``settings``, or an instance)
    emits on ``audio`` (a sound file, or mono float samples and their rate): one per utterance the
    vad service cuts (``vad``: its backend), or per span given (start and end in seconds)."""
    processor = analyser if isinstance(analyser, Processor) else \
        analyser(load_settings(analyser.Settings, analyser.service, env={}, **settings))
    samples, rate = _read(audio)
    fed = processor.stream_inputs()  # a second input that never ends a stream (a player's) gets nothing
    if len(fed) != 1:
        raise ValueError(f"{type(processor).__name__} takes {len(fed)} inputs; run_analyser feeds one")
    topic = next(iter(fed))
    if spans is not None:
        node = _LocalNode([_Source(samples, rate, topic, stream_id, spans), processor])
    else:
        from esiaf_services.vad.service import Vad, VadSettings  # the vad service cuts, as in a pipeline
        vad_settings = load_settings(VadSettings, "vad", env={}, backend=vad, input_topic=SOURCE_TOPIC,
                                     output_topic=topic)
        node = _LocalNode([_Source(samples, rate, SOURCE_TOPIC, stream_id), Vad(vad_settings), processor])
    node.run()
    return [_emitted(r) for r in node.results if r.component == processor.settings.name]


def _read(audio: str | Path | tuple[np.ndarray, int]) -> tuple[np.ndarray, int]:
    if isinstance(audio, tuple):
        samples, rate = audio
    else:
        import soundfile
        samples, rate = soundfile.read(str(audio), dtype="float32", always_2d=True)
        samples = samples.mean(axis=1)  # mono: channel counts are never converted on the way
    return np.asarray(samples, dtype=np.float32).reshape(-1), int(rate)


def _emitted(result: pb.Result) -> Emitted:
    field = result.WhichOneof("payload") or ""
    payload = {} if field in ("", "nothing") else MessageToDict(getattr(result, field),
                                                                preserving_proto_field_name=True)
    return Emitted(kind_of(result), result.span.start_ns, result.span.end_ns, result.stream_id, payload,
                   result.nothing.reason if field == "nothing" else "", result)


class _Source(Processor):
    """The file as 50 ms chunks on ``topic``; with ``spans``, only those, each ended as a VAD ends a segment."""

    service = "testing-source"

    def __init__(self, samples: np.ndarray, rate: int, topic: str, stream_id: str,
                 spans: Sequence[tuple[float, float]] | None = None):
        super().__init__(ComponentSettings(name=self.service, stream_id=stream_id))
        self.samples = (np.clip(samples, -1.0, 32767 / 32768) * 32768).astype(np.int16)
        self.rate, self.topic, self.spans = rate, topic, spans
        self.add_output(topic, AudioFormat(rate, "int16", channels=1))

    def _ns(self, sample: int) -> int:
        return sample * 1_000_000_000 // self.rate

    def produce(self) -> None:
        context = self._context()
        pieces = [(0, self.samples.size)] if self.spans is None else \
            [(round(a * self.rate), round(b * self.rate)) for a, b in self.spans]
        step = max(1, self.rate * CHUNK_MS // 1000)
        end = 0
        for first, last in pieces:
            if not 0 <= first < last <= self.samples.size:
                raise ValueError(f"span {first / self.rate:g}..{last / self.rate:g} s is not within the "
                                 f"audio's {self.samples.size / self.rate:g} s")
            for start in range(first, last, step):
                stop = min(start + step, last)
                segment = (self._ns(first), self._ns(last)) if self.spans is not None and stop == last else None
                context.publish(self.topic, self.samples[start:stop, None], self._ns(start), self._ns(stop),
                                segmentation_ended=segment is not None, segment=segment)
            end = last
        context.publish(self.topic, b"", self._ns(end), self._ns(end), end_of_stream=True)


class _LocalNode(Node):
    """Runs processors in order, each hearing what the ones before it publish; keeps the results.
    A handler's exception is raised, not counted: a test sees it."""

    strict = True

    def __init__(self, processors: Sequence[Processor]):
        super().__init__(processors)
        self.results: list[pb.Result] = []

    def run(self) -> int:
        for context in self.contexts:
            context.processor.setup()
            context.declared()
            context.output_links = {t: OutputLink(t, f) for t, f in context.processor.outputs.items()}
        try:
            self.contexts[0].processor.produce()
        finally:
            for context in self.contexts:
                context.processor.teardown()
        return self.exit_code

    def service(self, timeout_ms: float) -> None:
        """Nothing to service: no sockets."""

    def send_audio(self, context: Any, topic: str, msg: pb.AugmentedAudio) -> bool:
        self.deliver([topic_frame(topic, msg.stream_id), msg.SerializeToString()], after=context)
        return True

    def send_results(self, frames: list[bytes], stream_id: str) -> bool:
        if frames[0] == b"result":
            self.results.append(pb.Result.FromString(frames[1]))
        return True

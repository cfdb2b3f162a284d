"""Utterance features: openSMILE functionals (eGeMAPS v02 or ComParE 2016) of a whole segment.

The same code serves training (``tools/train.py``) and the running service, so a model sees
features computed exactly as it was trained on, over the same stretch of audio: the speech span
as the VAD's segmenter finds it, without the pre-roll and hang-over the VAD forwards around it
(``speech_span``; the models are trained on the spans of every way the VAD cuts). Functionals are
averages over every frame, so half a second of silence more or less changes them enough to flip
the label (tried: padding 40 EmoDB utterances with the VAD's 650 ms of silence took a 4-class
model's accuracy on them from 0.85 to 0.50).
"""
from __future__ import annotations

import functools
import importlib.util
from pathlib import Path
from typing import Any

import numpy as np

from esiaf.features import SharedExtractor, shared
from esiaf.speech.segmenter import ProbabilityParams, ProbabilitySegmenter, Segmenter, SegmenterParams, level_db
from esiaf.speech.windows import ChunkCutter, WindowCutter

# each set's configuration, under opensmile's config/ (its FeatureSet values)
FEATURE_SETS = {"eGeMAPSv02": "egemaps/v02/eGeMAPSv02", "ComParE_2016": "compare/ComParE_2016"}


class FeatureError(Exception):
    """Unknown feature set, or audio the extractor cannot use."""


class FeatureExtractor:
    """openSMILE functionals over a whole utterance: float32 vector of a fixed length.

    It runs openSMILE's own binding (``opensmile/core/lib.py``, ctypes over libSMILEapi) with the
    configuration and options ``opensmile.Smile`` gives it, and so computes exactly what
    ``Smile.process_signal`` returns (tested bit for bit), without importing the ``opensmile``
    package, whose pandas, pyarrow and audinterface would hold about 90 MB in every process."""

    def __init__(self, feature_set: str, sample_rate_hz: int = 16000):
        if feature_set not in FEATURE_SETS:
            raise FeatureError(f"unknown feature set {feature_set!r}; known: {', '.join(FEATURE_SETS)}")
        self.feature_set = feature_set
        self.sample_rate_hz = sample_rate_hz
        self._lib, root = _smile_binding()
        config = root / "config"
        self._config = str(config / f"{FEATURE_SETS[feature_set]}.conf")
        self._options: dict[str, object] = {  # Smile._options() and _extract(), functionals level
            "sink": str(config / "shared" / "standard_external_data_output_single.conf.inc"),
            "sinkLevel": "func",
            "bufferModeRbConf": str(config / "shared" / "BufferModeRb.conf.inc"),
            "frameModeFunctionalsConf": str(config / "shared" / "FrameModeFunctionals.conf.inc"),
            "source": str(config / "shared" / "standard_external_wave_input.conf.inc")}
        smile = self._smile(self._options)
        try:
            count = smile.external_sink_get_num_elements(SINK)
            self.names: list[str] = [smile.external_sink_get_element_name(SINK, i) for i in range(count)]
        finally:
            smile.free()

    def _smile(self, options: dict[str, object]) -> Any:
        smile = self._lib.OpenSMILE()
        smile.initialize(config_file=self._config, options=options, loglevel=2, log_file=None, debug=False)
        return smile

    @property
    def size(self) -> int:
        return len(self.names)

    def __call__(self, samples: np.ndarray) -> np.ndarray:
        """``samples``: mono float in [-1, 1] or int16, at ``sample_rate_hz``."""
        if samples.dtype != np.int16:  # as Smile does: scaled by 32768 and truncated
            samples = (np.asarray(samples, dtype=np.float32) * 32768).astype(np.int16)
        frames: list[np.ndarray] = []
        smile = self._smile({**self._options, "sampleRate": self.sample_rate_hz, "nBits": 16})
        try:
            smile.external_sink_set_callback_ex(SINK, lambda data, meta: frames.append(data.copy()))
            smile.external_audio_source_write_data(SOURCE, samples.tobytes())
            smile.external_audio_source_set_eoi(SOURCE)
            smile.run()
        finally:
            smile.free()
        vector = np.vstack(frames).astype(np.float32).reshape(-1) if frames else np.zeros(self.size, np.float32)
        if vector.shape[0] != self.size:
            raise FeatureError(f"{self.feature_set} gave {vector.shape[0]} values, expected {self.size}")
        return np.nan_to_num(vector, nan=0.0, posinf=0.0, neginf=0.0)


def without_digital_silence(samples: np.ndarray) -> np.ndarray:
    """``samples`` without the exact zeros at either end. A microphone never gives runs of exact zeros,
    but a file's padding, a muted input or a gap filled with zeros does, and the functionals of their
    log energies are extreme: 50-85 ms of zeros before an EmoDB utterance turned the emotion model's
    "neutral" at 0.99 into "happy" for 8 of 81 held-out utterances (a span starting 100 ms before
    the VAD's onset reaches into the zeros between files). Training and service both trim them."""
    nonzero = np.flatnonzero(samples)
    if not nonzero.size:
        return samples[:0]
    return samples[nonzero[0]:nonzero[-1] + 1]


SOURCE, SINK = "extsource", "extsink"  # the components opensmile's external input and output configs name


@functools.cache
def _smile_binding() -> tuple[Any, Path]:
    """opensmile's ctypes binding (core/lib.py) loaded alone, and its folder (config/ beside it)."""
    spec = importlib.util.find_spec("opensmile")  # found, not imported
    if spec is None or spec.origin is None:
        raise FeatureError("the opensmile package is missing: pip install -e '.[emotion]'")
    core = Path(spec.origin).parent / "core"
    lib_spec = importlib.util.spec_from_file_location("esiaf_opensmile_binding", core / "lib.py")
    if lib_spec is None or lib_spec.loader is None:
        raise FeatureError(f"cannot load openSMILE's binding {core / 'lib.py'}")
    module = importlib.util.module_from_spec(lib_spec)
    lib_spec.loader.exec_module(module)
    return module, core


def shared_extractor(feature_set: str, sample_rate_hz: int = 16000) -> SharedExtractor[FeatureExtractor]:
    """The process's one :class:`FeatureExtractor` of ``feature_set``: every classifier of this
    process that uses the set gets the same features of an utterance, computed once
    (``esiaf/features.py``); ``.extractor`` is the FeatureExtractor."""
    return shared(f"{feature_set}@{sample_rate_hz}", lambda: FeatureExtractor(feature_set, sample_rate_hz))


# how the vad service cuts, as its settings choose: the default first (backend silero, deciding per
# 32 ms window: the same spans at any chunk size), then silero deciding per chunk (``windows: false``;
# its spans at 20 ms chunks) and the energy backend (per 20 ms chunk)
VADS = ("silero", "silero-chunks", "energy")


def speech_span(samples: np.ndarray, sample_rate_hz: int, chunk_ms: float = 20.0,
                vad: str = "silero") -> tuple[int, int]:
    """(first, end) sample of what the vad service (cutting as ``vad`` says, see ``VADS``) would call
    speech in a recording of one utterance (float samples in [-1, 1]) played in ``chunk_ms``
    chunks: from the first segment's onset to the last segment's end; the whole recording if the
    VAD would find none. The three cut differently (Silero's span starts a little before the onset
    and ends after the last speech-like window, per window or per chunk; the energy segmenter's on
    its loud chunks), so the bundled models are trained on every one's spans (``tools/train.py``)."""
    segments = speech_segments(samples, sample_rate_hz, chunk_ms, vad)
    return (segments[0][0], segments[-1][1]) if segments else (0, len(samples))


def speech_segments(samples: np.ndarray, sample_rate_hz: int, chunk_ms: float = 20.0,
                    vad: str = "silero") -> list[tuple[int, int]]:
    """(first, end) sample of each segment the vad service would cut of a recording of one
    utterance (see ``speech_span``): more than one where a pause in it is longer than the VAD's
    ``min_silence_ms``; none if it hears no speech."""
    if vad not in VADS:
        raise FeatureError(f"unknown VAD {vad!r}; known: {', '.join(VADS)}")
    step = max(1, round(sample_rate_hz * chunk_ms / 1000))
    pad = 0
    cutter: Any = ChunkCutter()
    if vad != "energy":  # its state starts on half a second of silence, as in a stream between utterances
        pad = sample_rate_hz // 2
        samples = np.concatenate([np.zeros(pad, np.float32), samples, np.zeros(pad, np.float32)])
        segmenter: Any = ProbabilitySegmenter(ProbabilityParams())
        silero = _silero_model().stream(sample_rate_hz)
        if vad == "silero":
            cutter = WindowCutter(silero, samples.dtype.itemsize)
    else:
        segmenter = Segmenter(SegmenterParams())
    spans = []

    def ns(frames: int) -> int:
        return frames * 1_000_000_000 // sample_rate_hz

    for offset in range(0, len(samples), step):
        chunk = samples[offset:offset + step]
        last = offset + step >= len(samples)
        start_ns, end_ns = ns(offset), ns(offset + len(chunk))
        if isinstance(cutter, WindowCutter):
            pieces = cutter.cut(chunk.tobytes(), start_ns, end_ns, chunk, end_of_stream=last)
        else:
            if vad == "energy":
                score = level_db(float(np.max(np.abs(chunk))) if chunk.size else 0.0)
            else:
                score = silero.chunk_probability(chunk) if chunk.size else 0.0
            pieces = cutter.cut(b"", start_ns, end_ns, len(chunk), score, end_of_stream=last)
        for piece, score in pieces:
            for forward in segmenter.process(None, piece.start_ns, piece.end_ns, score,
                                             force_end=piece.end_of_stream):
                if forward.ended:
                    spans.append(forward.segment)
    length = len(samples) - 2 * pad
    out = []
    for start_ns, end_ns in spans:
        first = (start_ns * sample_rate_hz + 999_999_999) // 1_000_000_000 - pad
        end = end_ns * sample_rate_hz // 1_000_000_000 - pad
        out.append((min(max(0, first), length), min(max(0, end), length)))
    return out


@functools.cache
def _silero_model():
    from esiaf.speech.silero import SileroModel
    return SileroModel()

"""The pipeline's models in one process, one after the other, without transport: the baseline of
bench/latency.py and bench/dataset.py (the thesis' "pre-existing monolith", Fig. 5.7).

One loop reads a sound file in the grabber's default chunks (chunk_ms) stamped from sample counts
(paced in real time, or as fast as it goes) and segments it with the VAD's segmenter (``energy``: the original double
threshold; ``silero``: the neural VAD and its probability segmenter, the service's defaults, deciding per
32 ms window, or with ``windows=False`` per chunk, as the service does),
feeds the speech to pocketsphinx, and at each segment's end runs the emotion and gender models
(one openSMILE feature vector for both, as the hosted services share it) and, if asked, the
voiceid encoder. With ``array`` the SSL component (the service's own class and default settings)
hears all channels, chunk by chunk, and each utterance gets the circular mean of its frames; with
``beamformer`` too, the beamformer component steers the array at the talker from the SSL's meta
and the VAD hears its output, as in ``esiaf run --array``; otherwise the VAD hears the first
channel. CPU is counted per stage (``time.process_time`` around each).

    run = monolith(path, "robocup", fast=True, vad="silero", array="respeaker4", beamformer=True, voiceid=True)
    run.utterances[0].text, run.utterances[0].labels, run.cpu_s
"""
from __future__ import annotations

import math
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import soundfile

from esiaf import Audio
from esiaf.audio import SampleClock
from esiaf.formats import AudioFormat, encode, peak
from esiaf.runner import limit_native_threads
from esiaf.speech.classifiers import load_backend
from esiaf.speech.segmenter import ProbabilityParams, ProbabilitySegmenter, Segmenter, SegmenterParams, level_db
from esiaf.speech.silero import SileroModel
from esiaf.speech.windows import Piece, WindowCutter
from esiaf_services.asr.recognizer import PocketsphinxRecognizer
from esiaf_services.asr.service import resolve_grammar
from esiaf_services.grabber.service import GrabberSettings

CHUNK_MS = GrabberSettings.model_fields["chunk_ms"].default  # what esiaf run plays in, unless told
MIN_SPEECH_S = 0.5  # the utterance classifiers' min_speech_ms
MODELS = {"emotion": "emotion4", "gender": "gender"}


@dataclass
class Utterance:
    start_ns: int  # the speech span, capture time (the file's first sample at ``origin_ns``)
    end_ns: int
    closed_ns: int  # wall clock: when the segmenter closed the segment
    done_ns: dict[str, int] = field(default_factory=dict)  # wall clock: when each stage returned
    text: str = ""
    labels: dict[str, str] = field(default_factory=dict)  # emotion, gender
    azimuth_deg: float | None = None

    def latency_ms(self, stage: str) -> float:
        """From the segment's close to the stage's result."""
        return (self.done_ns[stage] - self.closed_ns) / 1e6


@dataclass
class MonolithRun:
    origin_ns: int
    utterances: list[Utterance]
    cpu_s: dict[str, float]  # per stage, while playing (models loaded before)
    wall_s: float


class _FrontEnd:
    """The ssl service's component fed chunk by chunk, its speech frames kept as (start, end, azimuth,
    confidence); with ``beamformer``, the beamformer component on what it forwards (the SSL meta with
    the audio), whose enhanced chunks are what the VAD hears, as in ``esiaf run --array``."""

    def __init__(self, array: str, rate: int, beamformer: bool):
        from esiaf_services.ssl.service import Ssl, SslSettings
        self.ssl = Ssl(SslSettings(sample_rate_hz=rate, array=array))
        self.ssl.setup()
        self.ssl.emit = self._emit  # type: ignore[method-assign,assignment]
        self.ssl.forward = self._forward  # type: ignore[method-assign,assignment]
        self.beamformer = None
        if beamformer:
            from esiaf_services.beamformer.service import Beamformer, BeamformerSettings
            self.beamformer = Beamformer(BeamformerSettings(sample_rate_hz=rate, array=array))
            self.beamformer.setup()
            self.beamformer.publish = self._publish  # type: ignore[method-assign,assignment]
        self.frames: list[tuple[int, int, float, float]] = []
        self.out: list[tuple[np.ndarray, int, int, bool]] = []  # mono int16 chunks for the VAD
        self.sequence = 0
        self.beamformer_cpu_s = 0.0

    def _emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None, **payload: Any) -> None:
        if "ssl" in payload:
            best = payload["ssl"].directions[0]
            self.frames.append((span[0], span[1], best.azimuth_deg, best.probability))

    def _forward(self, topic: str, audio: Audio, *, ssl_directions: Any = (), **meta: Any) -> int:
        if self.beamformer is not None:
            started = time.process_time()
            audio.meta.ssl_directions.extend(ssl_directions)
            self.beamformer.on_audio(audio)
            self.beamformer_cpu_s += time.process_time() - started
        return 0

    def _publish(self, topic: str, pcm: np.ndarray, start_ns: int, end_ns: int, *, end_of_stream: bool = False,
                 **meta: Any) -> int:
        self.out.append((pcm.reshape(-1, 1), start_ns, end_ns, end_of_stream))
        return 0

    def feed(self, chunk: np.ndarray, fmt: AudioFormat, start_ns: int, end_ns: int, last: bool
             ) -> list[tuple[np.ndarray, int, int, bool]]:
        """The chunks the VAD hears now: the beamformer's (late by the SSL frame), or the first microphone."""
        self.sequence += 1
        audio = Audio(topic=self.ssl.settings.input_topic, stream_id="monolith", publisher="monolith",
                      sequence=self.sequence, start_ns=start_ns, end_ns=end_ns, format=fmt, payload=encode(chunk, fmt))
        audio.meta.end_of_stream = last
        self.ssl.on_audio(audio)
        if self.beamformer is None:
            return [(chunk[:, :1], start_ns, end_ns, last)]
        out, self.out = self.out, []
        return out

    def azimuth(self, start_ns: int, end_ns: int) -> float | None:
        """Circular mean (weighted by confidence) of the frames within the span; None if there are none."""
        inside = [(az, p) for s, e, az, p in self.frames if s < end_ns and e > start_ns]
        self.frames = [f for f in self.frames if f[1] > start_ns]
        if not inside:
            return None
        x = sum(p * math.cos(math.radians(az)) for az, p in inside)
        y = sum(p * math.sin(math.radians(az)) for az, p in inside)
        return math.degrees(math.atan2(y, x)) % 360.0


def monolith(path: Path, grammar: str, *, fast: bool = False, vad: str = "energy", array: str = "",
             beamformer: bool = False, voiceid: bool = False, progress=None, windows: bool = True) -> MonolithRun:
    """Plays ``path`` through the models in this process; ``progress(seconds_played)`` every minute of audio."""
    limit_native_threads()  # one BLAS thread, as every ESIAF process has (a pool spins on a loaded machine)
    audio, rate = soundfile.read(str(path), dtype="int16", always_2d=True)
    fmt_all, fmt = AudioFormat(rate, "int16", channels=audio.shape[1]), AudioFormat(rate, "int16")
    recognizer = PocketsphinxRecognizer(sample_rate_hz=rate, grammar=resolve_grammar(grammar))
    from esiaf_services.emotion.service import MODELS as EMOTION_MODELS
    from esiaf_services.gender.service import MODELS as GENDER_MODELS
    folders = {"emotion": EMOTION_MODELS, "gender": GENDER_MODELS}  # each service's bundled models
    labellers = {name: load_backend("onnx", model, models_dir=folders[name]) for name, model in MODELS.items()}
    encoder = None
    if voiceid:
        from esiaf.speech.speaker.ge2e import shared_encoder
        encoder = shared_encoder()
    front = _FrontEnd(array, rate, beamformer) if array else None
    segmenter: Any
    if vad == "silero":
        silero = SileroModel().stream(rate)
        cutter: WindowCutter | None = WindowCutter(silero, frame_bytes=2) if windows else None
        segmenter = ProbabilitySegmenter(ProbabilityParams())
    else:
        silero, cutter, segmenter = None, None, Segmenter(SegmenterParams())
    cpu: dict[str, float] = defaultdict(float)
    step = round(rate * CHUNK_MS / 1000)
    cpu_start = time.process_time()
    origin_ns, started = time.time_ns(), time.monotonic()
    clock = SampleClock(origin_ns, rate)
    utterances: list[Utterance] = []
    forwarded: list[tuple[int, np.ndarray]] = []

    def stage(name: str, since: float) -> float:
        now = time.process_time()
        cpu[name] += now - since
        return now

    def close(forward: Any, t: float) -> float:
        """The segment's end: the recogniser's answer, then the utterance models, one after the other."""
        utterance = Utterance(forward.segment[0], forward.segment[1], time.time_ns())
        hypotheses = recognizer.finish()
        utterance.text = hypotheses[0].text if hypotheses else ""
        utterance.done_ns["asr"] = time.time_ns()
        t = stage("asr", t)
        first_ns = forwarded[0][0]  # the speech span only, as the services cut it
        samples = np.concatenate([item for _, item in forwarded])[:, 0].astype(np.float32) / 32768
        cut = samples[(utterance.start_ns - first_ns) * rate // 10**9:(utterance.end_ns - first_ns) * rate // 10**9]
        if cut.size >= MIN_SPEECH_S * rate:
            for name, labeller in labellers.items():
                scores = labeller.classify(cut)
                utterance.labels[name] = max(scores, key=scores.__getitem__)
                utterance.done_ns[name] = time.time_ns()
                t = stage(name, t)
            if encoder is not None:
                encoder.embed(cut)
                utterance.done_ns["voiceid"] = time.time_ns()
                t = stage("voiceid", t)
        if front is not None:
            utterance.azimuth_deg = front.azimuth(utterance.start_ns, utterance.end_ns)
            utterance.done_ns["ssl"] = time.time_ns()
            t = stage("ssl", t)
        utterance.done_ns["all"] = time.time_ns()
        utterances.append(utterance)
        return t

    for offset in range(0, len(audio), step):
        chunk = audio[offset:offset + step]
        start_ns, end_ns = clock.advance(len(chunk))
        if not fast:
            delay = started + (end_ns - origin_ns) / 1e9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        if progress is not None and offset // rate // 60 != (offset + step) // rate // 60:
            progress((offset + step) / rate)
        last = offset + step >= len(audio)
        t = time.process_time()
        heard = [(chunk[:, :1], start_ns, end_ns, last)]
        if front is not None:
            beamformer_cpu = front.beamformer_cpu_s
            heard = front.feed(chunk, fmt_all, start_ns, end_ns, last)
            cpu["beamformer"] += front.beamformer_cpu_s - beamformer_cpu  # within the ssl's forward
            t = stage("ssl", t + front.beamformer_cpu_s - beamformer_cpu)
        for mono, start_ns, end_ns, ended in heard:
            if cutter is not None:  # per Silero window, as the vad service decides
                pieces = cutter.cut(mono.tobytes(), start_ns, end_ns, mono[:, 0].astype(np.float32) / 32768, ended)
            else:
                score = (silero.chunk_probability(mono[:, 0].astype(np.float32) / 32768) if silero is not None
                         else level_db(peak(mono, fmt)))
                pieces = [(Piece(mono.tobytes(), start_ns, end_ns, 0, len(mono), ended), score)]
            forwards = []
            for piece, score in pieces:
                forwards += segmenter.process(piece, piece.start_ns, piece.end_ns, score, force_end=piece.end_of_stream)
            t = stage("vad", t)
            for forward in forwards:
                if not forwarded:
                    recognizer.start()
                piece = forward.item
                forwarded.append((piece.start_ns, np.frombuffer(piece.payload, dtype=np.int16).reshape(-1, 1)))
                recognizer.feed(piece.payload)
                t = stage("asr", t)
                if forward.ended:
                    t = close(forward, t)
                    forwarded = []
    cpu["loop"] = time.process_time() - cpu_start - sum(cpu.values())  # reading, pacing, cutting
    return MonolithRun(origin_ns, utterances, dict(cpu), time.monotonic() - started)


def _progress(played_s: float) -> None:
    print(f"monolith: {played_s / 60:.0f} min played", file=sys.stderr, flush=True)


def replay(path: Path, grammar: str, fast: bool, array: str) -> MonolithRun:
    """What bench/dataset.py runs in a child process: every model the pipeline runs by default."""
    return monolith(path, grammar, fast=fast, vad="silero", array=array, beamformer=bool(array), voiceid=True,
                    progress=_progress)

"""VAD service: forwards only speech audio and publishes a VAD result per segment.

Two backends:

- ``silero`` (the default): Silero VAD's speech probability per 32 ms window (ONNX, from the
  silero-vad wheel, on onnxruntime) segmented with hysteresis, minimum speech and silence
  durations, a pre-roll, and a maximum length cut at the least speech-like point
  (:class:`~esiaf.speech.segmenter.ProbabilitySegmenter`). It hears speech, not loudness, so
  babble and clatter 5-15 dB below the talker do not keep a segment open. It decides per window, not
  per transport chunk (:mod:`esiaf.speech.windows`): its segments are the same at any chunk
  size, and what it forwards is cut at window boundaries. With ``silero.windows: false`` it decides
  per chunk (the mean of the windows the chunk completes). The network hears level too: a person at
  -45 dBFS (10 dB below the robot's echo, on microphones set for that echo, once the echo canceller took
  it off) loses most of its speech-like windows. ``silero.level_max_gain_db`` (off by default) raises its
  input by a slow gain until a stream's loud windows reach ``silero.level_to_db`` (esiaf/speech/silero.py
  ``Leveller``): the quiet person is then heard, and so is the robot's residual echo, which only its
  quietness kept out (docs/benchmarks.md, "Double talk lost to the level").
- ``energy``: ESIAF's original double-threshold segmenter on the chunks' peak level.

The VAD result of a segment carries its mean speech probability (1 with ``energy``), and is emitted when
the segment ends. Earlier, once ``speech_start_ms`` of speech has been heard (Silero: from its first
window above ``silero.threshold``; less than ``silero.min_speech_ms``, which opens a segment), with
``speech_start_events`` a ``speech_start`` result says so (esiaf.results.speech_start: its span runs
from the speech's start to the capture time the vad decided), once per stretch of speech, and again within
it where Silero's probability rises sharply from a plateau (``silero.rise_to``, esiaf/speech/rise.py: a
person who starts over babble or residual echo that already opened the stretch; at most one per
``silero.rise_every_ms``); and at once, without waiting for ``speech_start_ms``, where it jumps from
quiet (``silero.jump_to``: the same rule from a quieter plateau, a person's onset; the stretch it opens is not
announced again): the orchestrator's barge-in (a person speaking while the robot plays) waits
neither for the utterance's end nor for its segment to open. Speech shorter than
``silero.min_speech_ms`` is announced too and never segmented (a cough): a barge-in on it is the price
of the shorter wait.

A vad that joins a stream after its start (its first message of the stream is not the publisher's first:
it was started, or restarted after a crash, while the stream went on) may join in the middle of an
utterance: it forwards nothing of a stream until it has heard a silence as long as one that ends a
segment, so no segment starts in the middle of speech (its end alone would be recognised as a wrong
sentence).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, ClassVar

from pydantic import Field

from esiaf import Audio, AudioFormat, BackendSettings, Component, SetupError
from esiaf.per_stream import PerStream
from esiaf.results import SPEECH_START, speech_start
from esiaf.settings import StrictModel
from esiaf.speech.rise import Rise, RiseParams
from esiaf.speech.segmenter import ProbabilityParams, ProbabilitySegmenter, Segmenter, SegmenterParams, level_db
from esiaf.speech.silero import RATES_HZ, Leveller, SileroError, SileroModel, SileroStream, window_frames
from esiaf.speech.windows import ChunkCutter, WindowCutter, messages

log = logging.getLogger(__name__)


class SileroSettings(StrictModel):
    """The silero backend's: Silero VAD's speech probability, segmented with hysteresis."""

    model_path: str = ""  # "" = silero_vad.onnx from the silero-vad wheel
    # decide per 32 ms window (the same segments at any chunk size, esiaf/speech/windows.py); false: per
    # chunk (a chunk's probability the mean of the windows it completes). The bundled emotion models are
    # trained on the spans of both (esiaf/speech/opensmile.py VADS)
    windows: bool = True
    threshold: float = 0.5  # a window at least this speech-like opens speech
    threshold_off: float = 0.35  # ... and one under this one is silence
    min_speech_ms: float = 250.0  # speech this long opens a segment
    min_silence_ms: float = 400.0  # silence this long closes it
    cut_search_ms: float = 2000.0  # a segment at max_ms is cut at its least speech-like point this far back
    onset_pad_ms: float = 100.0  # audio kept before the first speech-like window
    # a new speech_start within a stretch already announced (a person starting over babble or residual echo,
    # whose onset would otherwise get no barge-in; esiaf/speech/rise.py) on a sharp rise of the probability:
    rise_to: float = Field(default=0.75, ge=0, le=1)  # a window this speech-like (0: one speech_start per stretch)
    rise_from: float = Field(default=0.55, ge=0, le=1)  # ... after a plateau whose mean is at most this
    rise_by: float = Field(default=0.25, gt=0, le=1)  # ... and this much below the window
    rise_plateau_ms: float = Field(default=256.0, ge=32, le=5000)  # the plateau (before the rise's 64 ms)
    rise_every_ms: float = Field(default=1000.0, ge=0, le=60000)  # at most one per this after the last speech_start
    # a speech_start at once, without waiting for speech_start_ms, on a jump from quiet (a person's onset; the
    # same rule as the rise's, the same plateau and rate limit): a window this speech-like (0: no such start) ...
    jump_to: float = Field(default=0.5, ge=0, le=1)
    jump_from: float = Field(default=0.25, ge=0, le=1)  # ... after a plateau whose mean is at most this
    jump_by: float = Field(default=0.25, gt=0, le=1)  # ... and this much below the window
    # Silero's input (only) raised so that a stream's loud windows reach level_to_db (dBFS, 32 ms RMS; the 95th
    # percentile of the last 20 s), by at most level_max_gain_db (0: off, the default), the gain moving 2 dB/s at
    # most (esiaf/speech/silero.py Leveller). Off by default: it hears a quiet person over the robot, but the
    # robot's own residual echo too (docs/benchmarks.md, "Double talk lost to the level")
    level_to_db: float = Field(default=-20.0, ge=-60, le=0)
    level_max_gain_db: float = Field(default=0.0, ge=0, le=60)  # the most it raises (0: off, the default)


class EnergySettings(StrictModel):
    """The energy backend's: ESIAF's original double threshold on the chunks' peak level."""

    db_min: float = 65.0  # a chunk this loud opens speech (Pepper: 70)
    db_keep_alive: float = 60.0  # ... and one this loud keeps it open (Pepper: 65)
    keep_alive_ms: float = 400.0  # quieter for this long closes the segment


class VadSettings(BackendSettings):
    input_topic: str = "grabber/audio"
    output_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    sample_type: str = "int16"
    channels: int = 1
    backends: ClassVar[tuple[str, ...]] = ("silero", "energy")
    backend: str = "silero"  # silero | energy
    silero: SileroSettings = Field(default_factory=SileroSettings)
    energy: EnergySettings = Field(default_factory=EnergySettings)
    max_ms: float = 8000.0
    speech_start_events: bool = True  # a speech_start result as soon as speech begins (barge-in)
    speech_start_ms: float = 150.0  # ... once this much of it is heard (the segment opens at min_speech_ms)
    pre_roll_ms: float = 250.0
    # the flat names of the backends' settings, before they were nested
    renamed: ClassVar[dict[str, str]] = {
        **{name: f"silero.{name}" for name in SileroSettings.model_fields
           if not name.startswith(("rise_", "jump_", "level_"))},
        **{name: f"energy.{name}" for name in EnergySettings.model_fields}}


@dataclass
class VadStream:
    """One stream's segmenter, cutter, the Silero state when it decides per chunk, and whether it waits for
    the first silence (it joined the stream mid-way: the speech going on has no start here)."""
    segmenter: Any
    cutter: ChunkCutter | WindowCutter
    silero: SileroStream | None
    mid_speech: bool | None = None  # None: not known before its first message
    silence_ns: int = 0  # ... while it waits: how long it has been silent
    announced: bool = False  # the speech going on was announced (speech_start)
    rise: Rise | None = None  # silero with rise_to: a new talker's sharp rise within an announced stretch
    jump: Rise | None = None  # silero with jump_to: a jump from quiet, announced at once
    announced_ns: int = 0  # when the speech going on was last announced


class Vad(Component):
    """Voice activity detector: Silero VAD, or ESIAF's original double-threshold segmenter."""

    service = "vad"
    kind = "vad"
    Settings = VadSettings
    settings: VadSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {
        "backend": "silero (default: a neural VAD, robust to noise) or energy (the original)"}

    def __init__(self, settings: VadSettings):
        super().__init__(settings)
        self.rise_params: RiseParams | None = None
        self.jump_params: RiseParams | None = None
        if settings.backend == "silero" and settings.sample_rate_hz not in RATES_HZ:
            raise SetupError(f"the silero backend takes 8000 or 16000 Hz, not sample_rate_hz "
                             f"{settings.sample_rate_hz}")
        try:
            fmt = AudioFormat(settings.sample_rate_hz, settings.sample_type, channels=settings.channels)
            energy, silero = settings.energy, settings.silero
            if settings.backend == "energy":
                self.params: Any = SegmenterParams(energy.db_min, energy.db_keep_alive, energy.keep_alive_ms,
                                                   settings.max_ms, settings.pre_roll_ms)
            else:
                self.params = ProbabilityParams(silero.threshold, silero.threshold_off, silero.min_speech_ms,
                                                silero.min_silence_ms, settings.max_ms, settings.pre_roll_ms,
                                                silero.cut_search_ms, silero.onset_pad_ms)
                self.rise_params = RiseParams(silero.rise_to, silero.rise_from, silero.rise_by,
                                              silero.rise_plateau_ms) if silero.rise_to else None
                self.jump_params = RiseParams(silero.jump_to, silero.jump_from, silero.jump_by,
                                              silero.rise_plateau_ms) if silero.jump_to else None
        except ValueError as exc:
            raise SetupError(f"bad VAD settings: {exc}") from None
        self.add_input(settings.input_topic, fmt)
        self.add_output(settings.output_topic, fmt)
        self.model: SileroModel | None = None
        self.segmenters: PerStream[VadStream] = PerStream(self._new_stream, settings.max_streams, "segmenter",
                                                          info=self.info)
        self.segments = 0
        self._ended_on_chunk: set[str] = set()  # streams whose end was forwarded with their last segment

    def setup(self) -> None:
        if self.settings.backend == "silero":
            try:
                self.model = SileroModel(self.settings.silero.model_path)
            except SileroError as exc:
                raise SetupError(str(exc)) from None
            log.info("silero VAD model=%s threshold=%g/%g", self.model.path, self.settings.silero.threshold,
                     self.settings.silero.threshold_off)
        self.info["backend"] = self.settings.backend

    def _new_stream(self, stream_id: str) -> VadStream:
        if self.model is None:
            return VadStream(Segmenter(self.params), ChunkCutter(), None)
        rise = Rise(self.rise_params) if self.rise_params is not None else None
        jump = Rise(self.jump_params) if self.jump_params is not None else None
        if self.settings.silero.windows:  # cuts the payloads, which arrive in the declared input format
            frame_bytes = self.inputs[self.settings.input_topic].bytes_per_frame
            return VadStream(ProbabilitySegmenter(self.params),
                             WindowCutter(self._silero_stream(), frame_bytes), None, rise=rise, jump=jump)
        return VadStream(ProbabilitySegmenter(self.params), ChunkCutter(), self._silero_stream(), rise=rise, jump=jump)

    def _silero_stream(self) -> SileroStream:
        assert self.model is not None
        silero, rate = self.settings.silero, self.settings.sample_rate_hz
        leveller = Leveller(window_frames(rate), rate, silero.level_to_db, silero.level_max_gain_db) \
            if silero.level_max_gain_db > 0 else None
        return self.model.stream(rate, leveller)

    def on_audio(self, audio: Audio) -> None:
        stream = self.segmenters.get(audio.stream_id)
        segmenter, cutter, silero = stream.segmenter, stream.cutter, stream.silero
        if stream.mid_speech is None:  # its first message here: is it the stream's start?
            stream.mid_speech = audio.sequence > 1
        if isinstance(cutter, WindowCutter):  # one decision per Silero window, whatever the chunk
            pieces = cutter.cut(audio.payload, audio.start_ns, audio.end_ns,
                                audio.as_float()[:, 0], audio.end_of_stream)
        else:  # one decision per chunk: Silero's mean over the windows it completes, or its level
            if not audio.frames:
                score = 0.0 if silero is not None else float("-inf")
            elif silero is not None:
                score = silero.chunk_probability(audio.as_float()[:, 0])
            else:
                score = level_db(audio.peak())
            pieces = cutter.cut(audio.payload, audio.start_ns, audio.end_ns, audio.frames, score, audio.end_of_stream)
        forwards = []
        for piece, score in pieces:
            if stream.mid_speech:  # speech whose start this vad never heard is not segmented
                stream.silence_ns = stream.silence_ns + piece.end_ns - piece.start_ns if self._silent(score) else 0
                if stream.silence_ns < self._silence_ms * 1_000_000:
                    continue
                stream.mid_speech = False
                log.info("stream_id=%s joined at sequence %d: segmenting from its first silence, at start_ns=%d",
                         audio.stream_id, audio.sequence, piece.start_ns)
            forwards += segmenter.process(piece, piece.start_ns, piece.end_ns, score, force_end=piece.end_of_stream)
            if self.settings.speech_start_events:
                self._announce(stream, audio.stream_id, piece.start_ns, piece.end_ns, score)
        heard = segmenter.speech_heard if segmenter.active else None
        speech_until_ns = heard[0] + heard[1] if heard is not None else 0  # the open utterance's last speech
        for message in messages(forwards, audio.format.sample_rate_hz):
            piece, forward = message.piece, message.forward
            end_of_stream = forward.ended and piece.end_of_stream
            self.publish(self.settings.output_topic, piece.payload, piece.start_ns, piece.end_ns,
                         stream_id=audio.stream_id, segmentation_ended=forward.ended, segment=forward.segment,
                         end_of_stream=end_of_stream, speech_until_ns=0 if forward.ended else speech_until_ns)
            if end_of_stream:
                self._ended_on_chunk.add(audio.stream_id)
            if forward.segment is not None:  # the segment ended: its speech span
                self.segments += 1
                self.info["segments"] = self.segments
                self.emit("vad", forward.segment, stream_id=audio.stream_id, vad={"probability": forward.probability})
                log.info("segment stream_id=%s start_ns=%d end_ns=%d", audio.stream_id, *forward.segment)

    def _announce(self, stream: VadStream, stream_id: str, start_ns: int, now_ns: int, score: float) -> None:
        """A speech_start result once speech has gone on for speech_start_ms (or opened a segment), once
        per stretch of speech; at once on a jump of the probability from quiet (a person's onset); and again
        within a stretch on a sharp rise of the probability (a new talker). A jump or rise comes at most once
        per rise_every_ms after the last speech_start; a jump announces the stretch it starts (the segmenter
        hears speech there: ``jump_to`` below ``threshold`` jumps only where a window reaches ``threshold``)."""
        rise_onset_ns = stream.rise.window(start_ns, now_ns, score) if stream.rise is not None else None
        jump_onset_ns = stream.jump.window(start_ns, now_ns, score) if stream.jump is not None else None
        heard = stream.segmenter.speech_heard
        rested = now_ns - stream.announced_ns >= self.settings.silero.rise_every_ms * 1e6
        if jump_onset_ns is not None and heard is not None and rested:  # a jump from quiet: at once
            stream.announced = True
            onset_ns = jump_onset_ns
            log.info("stream_id=%s speech_start on a jump from quiet: onset_ns=%d probability=%.2f",
                     stream_id, onset_ns, score)
        elif heard is None:
            stream.announced = False
            return
        elif not stream.announced and (heard[1] >= self.settings.speech_start_ms * 1e6 or stream.segmenter.active):
            stream.announced = True
            onset_ns = heard[0]
        elif not (stream.announced and rise_onset_ns is not None and rested):
            return
        else:  # a new talker within the stretch announced
            onset_ns = rise_onset_ns
            log.info("stream_id=%s speech_start on a rise within a stretch: onset_ns=%d probability=%.2f",
                     stream_id, onset_ns, score)
        stream.announced_ns = now_ns
        probability = score if self.settings.backend == "silero" else 1.0
        self.emit(SPEECH_START, (onset_ns, max(onset_ns, now_ns)), stream_id=stream_id,
                  generic=speech_start(probability))

    def _silent(self, score: float) -> bool:
        """A window or chunk that is no speech (below the threshold that keeps a segment going)."""
        settings = self.settings
        return score < (settings.silero.threshold_off if self.model is not None else settings.energy.db_keep_alive)

    @property
    def _silence_ms(self) -> float:
        """A silence as long as this ends a segment."""
        settings = self.settings
        return settings.silero.min_silence_ms if self.model is not None else settings.energy.keep_alive_ms

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        self.segmenters.pop(stream_id)
        if stream_id in self._ended_on_chunk:
            self._ended_on_chunk.discard(stream_id)
        else:  # no segment was open: tell consumers with an empty chunk
            super().on_end_of_stream(stream_id, audio)

"""Echo canceller service: the robot's own voice taken out of every microphone channel.

Inputs: the microphones (``input_topic``, N channels, as their producer declares them) and the
loudspeaker's reference (``reference_topic``, mono: what the player sent to the loudspeaker, stamped
with the capture clock at the time it is played). Output: the same N channels on ``output_topic``,
with the microphones' own capture times, so ssl, the beamformer and the vad run on it unchanged.

Per stream (each robot has its own player, publishing under the robot's stream id):

- **no reference** (no player, or the player has been quiet for longer than the echo lasts): each
  chunk is passed on as it came, byte for byte;
- **the robot speaks**: a chunk waits until the reference covering it has arrived (at most
  ``hold_ms`` of capture time; the player publishes what it plays before the echo comes back), then
  is cancelled (esiaf_services/aec/core.py: delay and clock drift estimated from the signals) and
  published once its cancelled frames are complete. After the reference's last sample the canceller
  keeps on for the estimated delay plus ``tail_ms`` (the room's echo), then passes again;
- **a replay** (``expect_reference``: ``esiaf run --playback``): every chunk waits for its reference,
  however fast the microphones come (``hold_ms`` is then long), until the reference ends;
- **while it cancels**, ``echo`` events (esiaf.results.ECHO) measure its output per block
  (esiaf_services/aec/evidence.py): fusion tells a person who speaks over the robot from the robot's
  residual echo by them;
- **a reference that stops arriving mid-utterance** (no chunk for ``reference_timeout_ms`` of capture
  time and its last chunk did not end the utterance): pass-through, said once in the log until the
  reference comes back.

A reference at another rate is converted by the SDK; at another channel count the orchestrator
refuses the later registration of the two with the reason (channel counts are never converted).
Backends: esiaf_services/aec/backends.py; the choice and its figures: esiaf_services/aec/README.md.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import Field

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError
from esiaf.api_client import declared_format
from esiaf.per_stream import PerStream
from esiaf.results import ECHO, echo
from esiaf_services.aec.backends import BACKENDS, BackendError, Canceller
from esiaf_services.aec.core import StreamCanceller
from esiaf_services.aec.evidence import CONVERGE_S, EchoMeter

log = logging.getLogger(__name__)
MS = 1_000_000


class AecSettings(ComponentSettings):
    input_topic: str = "grabber/audio"
    reference_topic: str = "player/audio"
    output_topic: str = "aec/audio"
    backend: str = "speex"  # speex | webrtc (esiaf_services/aec/README.md: why speex, with figures)
    channels: int = 0  # of the input; 0 = as its producer declares (asked from the orchestrator)
    sample_rate_hz: int = 16000  # of the input and the reference (the SDK converts a reference's rate)
    max_delay_ms: float = 400.0  # the longest delay from the reference's stamps to the echo looked for
    hold_ms: float = 150.0  # the longest a chunk waits (in capture time) for the reference covering it
    tail_ms: float = 500.0  # cancel on this long after the reference's last sample (plus the delay)
    reference_timeout_ms: float = 500.0  # a reference silent this long without ending: pass-through
    suppress_residual: bool = True  # speex's residual echo suppressor on the output (the echo events always judge one)
    residual_db: int = Field(default=-40, ge=-100, le=0)  # it lowers what is left of the echo alone by this much
    # ... and while someone near speaks too: 0 keeps a person over the robot (aec README: how it was chosen)
    residual_active_db: int = Field(default=0, ge=-100, le=0)
    expect_reference: bool = False  # a replay's: every stream has one from its start (esiaf run --playback)
    # fit the drift once 3 delay estimates span this long (0.5: the fast start, README; 3.0 before it)
    drift_fit_min_s: float = Field(default=0.5, ge=0.0, le=60.0)
    # on a new alignment, adapt this often over the last second again (2: the fast start; 0: off, before it)
    retrain_passes: int = Field(default=2, ge=0, le=10)
    # a delay estimate this far off the fitted line waits for a second that agrees before the line moves
    # (0.5: README, "An estimate off the line"; 20: before, where one such estimate lost the echo twice)
    delay_outlier_ms: float = Field(default=0.5, ge=0.05, le=20.0)


@dataclass
class StreamState:
    canceller: StreamCanceller | None = None  # made at the stream's first reference
    reference_end_ns: int = 0  # stamp of the end of the last reference chunk
    reference_ended: bool = True  # its last chunk ended the utterance (or there is none yet)
    stalled: bool = False  # the reference stopped arriving mid-utterance: passing through
    microphones_ended: bool = False  # their last chunk is waiting
    waiting: list[Audio] = field(default_factory=list)  # chunks held for the reference or for their frames
    fed: int = 0  # of the waiting chunks, how many the canceller has had
    ready: list[np.ndarray] = field(default_factory=list)  # cancelled frames not yet published
    ready_frames: int = 0
    meter: EchoMeter | None = None  # the cancelled output's blocks (echo events), from the first one


class EchoCanceller(Component):
    """Cancels the loudspeaker's echo (``player/audio``) from each microphone channel."""

    service = "aec"
    kind = "other"
    Settings = AecSettings
    settings: AecSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {"backend": "speex (default) or webrtc (AEC3)",
                                         "input_topic": "the microphones' topic"}

    def __init__(self, settings: AecSettings):
        super().__init__(settings)
        if settings.backend not in BACKENDS:
            raise SetupError(f"unknown aec backend {settings.backend!r}; known: {', '.join(BACKENDS)}")
        self.format: AudioFormat | None = None
        self.streams: PerStream[StreamState] = PerStream(lambda _: StreamState(), settings.max_streams, "aec",
                                                         info=self.info)
        self.passed = 0  # chunks passed through unchanged
        self.cancelled = 0  # chunks published cancelled
        self.info.update(backend=settings.backend)

    def setup(self) -> None:
        s = self.settings
        if s.channels:
            try:
                fmt = AudioFormat(s.sample_rate_hz, "int16", channels=s.channels)
            except ValueError as exc:
                raise SetupError(f"bad aec input format: {exc}") from None
        else:
            declared = declared_format(s.orchestrator_url, s.input_topic, s.register_timeout_s, lambda: self.stopping)
            if declared is None:
                raise SetupError(f"no producer of {s.input_topic!r} registered with {s.orchestrator_url} within "
                                 f"{s.register_timeout_s:g} s; start it first or set channels")
            fmt = AudioFormat(s.sample_rate_hz, "int16", channels=AudioFormat.from_dict(declared).channels)
        self._new_canceller(fmt.channels)  # a missing library or a bad rate fails here, not at the first reference
        self.format = fmt
        self.add_input(s.input_topic, fmt)
        self.add_input(s.reference_topic, AudioFormat(s.sample_rate_hz, "int16", channels=1))
        self.add_output(s.output_topic, fmt)
        log.info("cancelling echo input=%s reference=%s output=%s format=%s backend=%s", s.input_topic,
                 s.reference_topic, s.output_topic, fmt, s.backend)

    def _new_canceller(self, channels: int) -> StreamCanceller:
        try:
            s = self.settings
            # the echo events judge speex's output as fusion's rule was calibrated on (its suppressor's
            # defaults) while the published one keeps more of a person speaking over the robot
            options = ({"suppress_residual": s.suppress_residual, "residual_db": s.residual_db,
                        "residual_active_db": s.residual_active_db, "judge": True} if s.backend == "speex" else {})
            backend: Canceller = BACKENDS[s.backend](channels, s.sample_rate_hz, **options)
        except BackendError as exc:
            raise SetupError(str(exc)) from None
        return StreamCanceller(backend, self.settings.sample_rate_hz, max_delay_ms=self.settings.max_delay_ms,
                               fit_min_s=self.settings.drift_fit_min_s, retrain_passes=self.settings.retrain_passes,
                               outlier_ms=self.settings.delay_outlier_ms)

    # -- the reference ------------------------------------------------------------------
    def on_audio(self, audio: Audio) -> None:
        if audio.topic == self.settings.reference_topic:
            self._on_reference(audio)
        else:
            self._on_microphones(audio)

    def _on_reference(self, audio: Audio) -> None:
        state = self.streams.get(audio.stream_id)
        if state.canceller is None:
            assert self.format is not None  # set by setup()
            state.canceller = self._new_canceller(self.format.channels)
        if not state.reference_end_ns and audio.frames:
            log.info("stream_id=%s: the loudspeaker's reference arrived; cancelling its echo", audio.stream_id)
        if audio.frames:
            state.canceller.add_reference(audio.start_ns, audio.as_float()[:, 0])
            state.reference_end_ns = max(state.reference_end_ns, audio.end_ns)
            if state.stalled:
                state.stalled = False
                log.info("stream_id=%s: the reference arrives again; cancelling", audio.stream_id)
        state.reference_ended = audio.segmentation_ended or audio.end_of_stream
        self._drain(audio.stream_id, state)

    # -- the microphones ----------------------------------------------------------------
    def _on_microphones(self, audio: Audio) -> None:
        state = self.streams.get(audio.stream_id)
        if state.canceller is None and self.settings.expect_reference:  # its chunks wait for the reference
            assert self.format is not None  # set by setup()
            state.canceller, state.reference_ended = self._new_canceller(self.format.channels), False
        if not state.waiting and not self._echo_possible(state, audio):
            self.passed += 1
            self.forward(self.settings.output_topic, audio, end_of_stream=audio.end_of_stream)
            if audio.end_of_stream:
                self.streams.pop(audio.stream_id)
            return
        state.waiting.append(audio)
        state.microphones_ended = audio.end_of_stream
        self._drain(audio.stream_id, state)

    def _echo_possible(self, state: StreamState, audio: Audio) -> bool:
        """Whether the loudspeaker's echo may be in ``audio``: the robot spoke recently enough."""
        if state.canceller is None or state.stalled:
            return False
        if not state.reference_end_ns:  # expected, not here yet
            return self.settings.expect_reference
        delay_ns = state.canceller.delay_ns(state.reference_end_ns)
        return audio.start_ns < state.reference_end_ns + max(delay_ns, 0) + self.settings.tail_ms * MS

    def _reference_ready(self, state: StreamState, audio: Audio, newest_end_ns: int) -> bool:
        """Whether ``audio`` can be cancelled now: its reference is in, over, or waited for long enough (or, live,
        the microphones have ended: nothing more will come to wait for)."""
        assert state.canceller is not None  # a chunk waits only once the stream has a reference
        if state.reference_end_ns >= state.canceller.reference_needed_until(audio.end_ns) or state.reference_ended:
            return True
        if state.microphones_ended and not self.settings.expect_reference:
            return True
        return newest_end_ns - audio.end_ns >= self.settings.hold_ms * MS

    def _drain(self, stream_id: str, state: StreamState) -> None:
        """Feeds the waiting chunks whose reference is ready to the canceller, publishes those whose frames are
        complete; a stalled reference, the end of the echo or of the stream flushes; a stall passes the rest."""
        if not state.waiting:
            return
        self._feed(stream_id, state)
        all_fed = state.fed == len(state.waiting)
        finished = state.microphones_ended and all_fed
        stalled = state.stalled and not all_fed
        if state.canceller is not None and (finished or stalled or
                                            (all_fed and not self._echo_possible(state, state.waiting[-1]))):
            self._take(state, state.canceller.flush())
        self._publish_ready(state, end_of_stream=finished)
        if stalled:  # what the canceller never had passes unchanged
            for index, audio in enumerate(state.waiting):
                self.passed += 1
                self.forward(self.settings.output_topic, audio,
                             end_of_stream=state.microphones_ended and index == len(state.waiting) - 1)
            state.waiting, state.fed = [], 0
        if state.microphones_ended and not state.waiting:
            self.streams.pop(stream_id)

    def _feed(self, stream_id: str, state: StreamState) -> None:
        canceller = state.canceller
        newest_end_ns = state.waiting[-1].end_ns
        while state.fed < len(state.waiting):
            audio = state.waiting[state.fed]
            if canceller is None or state.stalled or not self._reference_ready(state, audio, newest_end_ns):
                return
            if not state.reference_ended and audio.start_ns - state.reference_end_ns >= \
                    self.settings.reference_timeout_ms * MS:
                state.stalled = True
                log.warning("stream_id=%s: the loudspeaker's reference stopped arriving mid-utterance (last at "
                            "%d, %g ms ago in capture time); passing the microphones through until it is back",
                            stream_id, state.reference_end_ns, (audio.start_ns - state.reference_end_ns) / MS)
                return
            self._take(state, canceller.process(audio.start_ns, audio.samples))
            state.fed += 1

    def _take(self, state: StreamState, frames: np.ndarray) -> None:
        if len(frames):
            state.ready.append(frames)
            state.ready_frames += len(frames)

    def _publish_ready(self, state: StreamState, end_of_stream: bool) -> None:
        ready = np.concatenate(state.ready) if state.ready else np.zeros((0, 1), dtype=np.int16)
        used = 0
        while state.fed and len(ready) - used >= state.waiting[0].frames:
            audio = state.waiting.pop(0)
            state.fed -= 1
            frames = ready[used:used + audio.frames]
            used += audio.frames
            self.cancelled += 1
            channels = audio.format.channels
            self._measure(state, audio, frames[:, channels:] if frames.shape[1] > channels else frames)
            frames = frames[:, :channels]
            self.publish(self.settings.output_topic, frames if audio.frames else b"", audio.start_ns, audio.end_ns,
                         stream_id=audio.stream_id, end_of_stream=end_of_stream and not state.waiting)
        rest = ready[used:]
        state.ready, state.ready_frames = ([rest] if len(rest) else []), len(rest)

    def _measure(self, state: StreamState, audio: Audio, frames: np.ndarray) -> None:
        """The ``echo`` events of the blocks of cancelled output that ``frames`` complete."""
        if not audio.frames or state.canceller is None:
            return
        if state.meter is None:
            state.meter = EchoMeter(self.settings.sample_rate_hz)
        converged = state.canceller.converged_at(audio.start_ns, CONVERGE_S)
        for block in state.meter.add(audio.start_ns, audio.samples, frames, converged):
            self.emit(ECHO, (block.start_ns, block.end_ns), stream_id=audio.stream_id,
                      generic=echo(block.level_db, block.above_floor_db, block.cancelled_db, block.converged))

    def stream_inputs(self) -> set[str]:
        """The microphones' end ends a stream; the player's may never come (a robot talks on and off)."""
        return {self.settings.input_topic}

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """The microphones' last chunk carried the end already."""

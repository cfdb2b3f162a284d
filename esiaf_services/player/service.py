"""Player service: plays what the robot says and publishes it as the echo canceller's reference.

It plays sound files and sentences (flite) to an ALSA playback device (``device``) or to a file or
FIFO (``output``: raw s16le, or WAV by its suffix), one item after the other, in ``chunk_ms`` chunks.
Every chunk it sends to the loudspeaker is published on ``player/audio`` (mono int16), stamped in
the capture clock with the time it is played: the first chunk of an item when it is written, the
rest by sample count from there (a device plays at its own pace; a file is paced in real time
unless ``fast``). The last chunk of an item ends the utterance (``segmentation_ended``), so the
echo canceller knows the robot stopped on purpose; an item stopped early ends with an empty chunk.

Work comes from ``input`` and ``say`` (played at start: ``esiaf run --playback``), from
:meth:`Player.play` and :meth:`Player.say_text` (any thread), or from the orchestrator's commands
(:meth:`Player.on_command`: ``POST /streams/{stream}/say`` and ``/play``, ``DELETE
/streams/{stream}/playing``, and a barge-in under the stream's policy, docs/protocol.md "Commands").

The orchestrator knows what plays: when an item starts, each part of it that sounds (above
``SILENT_DBFS``, pauses shorter than ``PAUSE_S`` bridged) is reported as a ``playback`` result (a kind of
its own: ``text`` the item's name, ``attributes`` ``{"item": n, "part": k, "stopped": false}``) spanning
the capture time it is to play: a recorded robot voice with long silences (``esiaf run --playback``)
is not "playing" in them. An item stopped early (a stop, a barge-in under ``stop``, the player stopping)
has each part not played to its end reported again with its real end (``"stopped": true``; a part not
begun: zero length at the stop): the later result of a part revises the earlier. While an item plays,
the heartbeat's info carries ``playing``: its name and span in capture time (a heartbeat goes out when
it starts and ends). A barge-in under ``duck`` plays the rest of the
current item ``duck_db`` lower.

``follow_stream`` stamps the first item as played from the start of the player's stream as its
grabber announced it to the orchestrator (waiting for it), so a recorded robot voice lines up with
a recorded microphone file (``esiaf run --input MICS.wav --playback ROBOT.wav``); a replay's player
publishes as its grabber does (waiting for the consumers, not dropping at the high-water mark). A file sink is
written ``ahead_ms`` before the stamps say it is played (unless ``fast``): the echo canceller
has the reference before the echo.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import httpx
import numpy as np

from esiaf import AudioFormat, Component, ComponentSettings, SampleClock, SetupError
from esiaf.api_client import OrchestratorHTTP
from esiaf.control_messages import BargeIn, Command, Play, Say, StopPlaying
from esiaf.results import PLAYBACK, playback
from esiaf_services.player.sinks import AlsaSink, FileSink
from esiaf_services.player.tts import SpeechError, say

log = logging.getLogger(__name__)
IDLE_POLL_S = 0.02  # how soon a new item starts when the player is idle
SILENT_DBFS = -50.0  # a 20 ms frame below this level (dB re full scale RMS) is silence in a playback report
PAUSE_S = 0.5  # ... and a silence shorter than this within a part does not end it


class PlayerSettings(ComponentSettings):
    device: str = ""  # ALSA playback device (aplay -L)
    output: str = ""  # ... or a file or FIFO to write to (raw s16le; WAV if it ends in .wav)
    input: str = ""  # a sound file to play at start
    # ... what the robot says in it: a JSON list of {"start_s", "text"} on its timeline (esiaf run --playback
    # takes ROBOT.json beside ROBOT.wav); each part that sounds is reported as saying the texts starting in it
    transcript: str = ""
    say: str = ""  # a sentence to say at start (after input)
    voice: str = "slt"  # flite voice
    topic: str = "player/audio"
    sample_rate_hz: int = 16000
    chunk_ms: float = 20.0  # what a stop waits for at most, and the ALSA period
    fast: bool = False  # a file output written as fast as possible
    ahead_ms: float = 200.0  # a file output is written this long before it is played
    follow_stream: bool = False  # the first item plays from the stream's start (a replay's timeline)
    exit_when_done: bool = False  # stop once input and say are played
    wait_for_subscribers: int = 0  # before the first item, wait until the topic has this many subscribers
    wait_timeout_s: float = 30.0
    duck_db: float = 15.0  # a barge-in under the duck policy plays the rest of the item this much lower


@dataclass
class Item:
    name: str
    samples: np.ndarray  # float, full scale 1, at the player's rate
    said: list[tuple[float, str]] = field(default_factory=list)  # its transcript: (start_s, text), by start


class Player(Component):
    """Plays sound files and flite sentences; publishes what it plays on player/audio."""

    service = "player"
    kind = PLAYBACK  # its results: what it plays, when
    Settings = PlayerSettings
    settings: PlayerSettings  # an instance of Settings: its fields, for type checkers
    options: ClassVar[dict[str, str]] = {"device": "ALSA playback device (see aplay -L)",
                                         "output": "file or FIFO to play to instead of a device",
                                         "input": "sound file to play at start", "say": "sentence to say at start",
                                         "transcript": "what the input says: JSON [{start_s, text}]"}

    def __init__(self, settings: PlayerSettings):
        super().__init__(settings)
        if bool(settings.device) == bool(settings.output):
            raise SetupError("give exactly one of an ALSA playback device (--device) or an output file (--output)")
        if settings.chunk_ms <= 0:
            raise SetupError(f"chunk_ms must be positive, not {settings.chunk_ms}")
        try:
            self.format = AudioFormat(settings.sample_rate_hz, "int16", channels=1)
        except ValueError as exc:
            raise SetupError(f"bad player format: {exc}") from None
        self.chunk_frames = max(1, round(settings.sample_rate_hz * settings.chunk_ms / 1000))
        self.add_output(settings.topic, self.format)
        self._queue: deque[Item] = deque()
        self._lock = threading.Lock()
        self._cut = threading.Event()  # stop_playing(): the current item ends at its next chunk
        self.sink: AlsaSink | FileSink | None = None
        self.played = 0  # items played to their end or stopped
        self.items = 0  # items started: each playback result names its item's number
        self._gain = 1.0  # the current item's (a duck lowers it)
        if settings.transcript and not settings.input:
            raise SetupError("a transcript (--transcript) says what the input file says: give --input too")
        if settings.input:  # read early: a bad file fails before registration
            self.play_file(Path(settings.input), read_transcript(Path(settings.transcript))
                           if settings.transcript else [])
        if settings.say:
            try:
                self.say_text(settings.say, settings.voice)
            except SpeechError as exc:
                raise SetupError(str(exc)) from None

    def setup(self) -> None:
        s = self.settings
        self.sink = AlsaSink(s.device, s.sample_rate_hz, self.chunk_frames) if s.device else \
            FileSink(Path(s.output), s.sample_rate_hz)
        log.info("player ready sink=%s format=%s", s.device or s.output, self.format)

    # -- what to play (any thread) ------------------------------------------------------
    def play(self, samples: np.ndarray, name: str, said: list[tuple[float, str]] | None = None) -> None:
        """Queues mono float samples (full scale 1) at the player's rate; ``said``: its transcript."""
        with self._lock:
            self._queue.append(Item(name, np.clip(np.asarray(samples, dtype=np.float64), -1.0, 1.0),
                                    sorted(said or [])))

    def play_file(self, path: Path, said: list[tuple[float, str]] | None = None) -> None:
        import soundfile
        import soxr
        try:
            samples, rate = soundfile.read(str(path), dtype="float64", always_2d=True)
        except (RuntimeError, soundfile.LibsndfileError) as exc:
            raise SetupError(f"cannot read {path}: {exc}") from None
        if samples.shape[1] != 1:
            raise SetupError(f"{path} has {samples.shape[1]} channels; the player plays mono")
        mono = samples[:, 0]
        self.play(soxr.resample(mono, rate, self.format.sample_rate_hz) if rate != self.format.sample_rate_hz
                  else mono, path.name, said)

    def say_text(self, text: str, voice: str = "slt") -> None:
        """Queues ``text`` spoken by flite; SpeechError if it cannot be."""
        self.play(say(text, voice, self.format.sample_rate_hz), f"say: {text}")

    def stop_playing(self) -> None:
        """Ends the current item now and forgets the queued ones."""
        with self._lock:
            self._queue.clear()
        self._cut.set()

    def on_command(self, command: Command) -> None:
        """The orchestrator's orders for its stream (on the data thread: between two chunks while it plays)."""
        if command.stream_id != self.settings.stream_id:
            log.warning("ignored order=%s for stream_id=%s: this player plays stream_id=%s", command.order.action,
                        command.stream_id, self.settings.stream_id)
            return
        order = command.order
        if isinstance(order, Say):
            try:
                self.say_text(order.text, order.voice)
            except SpeechError as exc:
                log.warning("cannot say %r: %s", order.text[:80], exc)
        elif isinstance(order, Play):
            pcm = np.frombuffer(order.pcm[:len(order.pcm) // 2 * 2], dtype="<i2")
            self.play(pcm.astype(np.float64) / 32768.0, order.name)
        elif isinstance(order, StopPlaying):
            self.stop_playing()
        elif isinstance(order, BargeIn) and self.info.get("playing"):
            log.info("barge-in at capture_ns=%d policy=%s", order.capture_ns, order.policy)
            if order.policy == "stop":
                self.stop_playing()
            elif order.policy == "duck":
                self._gain = 10 ** (-abs(self.settings.duck_db) / 20)

    # -- playing ------------------------------------------------------------------------
    def produce(self) -> None:
        s = self.settings
        if s.wait_for_subscribers and not self.wait_for_subscribers(s.topic, s.wait_for_subscribers,
                                                                     s.wait_timeout_s) and not self.stopping:
            log.warning("topic=%s has fewer than %d subscribers after %g s; playing anyway", s.topic,
                        s.wait_for_subscribers, s.wait_timeout_s)
        first = True
        while not self.stopping:
            with self._lock:
                item = self._queue.popleft() if self._queue else None
            if item is None:
                if self.settings.exit_when_done:
                    break
                self.sleep_until(time.monotonic() + IDLE_POLL_S)
                continue
            origin_ns = self._stream_start() if first and self.settings.follow_stream else self.clock_ns()
            first = False
            self._play(item, origin_ns)
        if self.settings.exit_when_done and not self.stopping:
            now_ns = self.clock_ns()
            self.publish(self.settings.topic, b"", now_ns, now_ns, end_of_stream=True)
            self.stop()

    def _stream_start(self) -> int:
        """The capture time the player's stream started at, as announced (waiting for it)."""
        s = self.settings
        deadline = time.monotonic() + s.wait_timeout_s
        with OrchestratorHTTP(s.orchestrator_url) as http:
            while not self.stopping:
                try:
                    response = http.get(f"/streams/{s.stream_id}")
                    if response.status_code == 200:
                        stream = response.json()
                        # a replay's audio (--fast) waits for its consumers: so does the player's then
                        self.join_stream(s.stream_id, stream["info"].get("realtime") is False)
                        return int(stream["start_ns"])
                except (httpx.HTTPError, ValueError, KeyError) as exc:
                    log.info("waiting for the orchestrator: %s", exc)
                if time.monotonic() >= deadline:
                    break
                self.sleep_until(time.monotonic() + IDLE_POLL_S * 5)
        log.warning("stream_id=%s was not announced within %g s: playing from now", s.stream_id, s.wait_timeout_s)
        return self.clock_ns()

    def _play(self, item: Item, origin_ns: int) -> None:
        sink = self.sink
        assert sink is not None  # setup() made it
        self._cut.clear()
        self._gain = 1.0
        pcm = np.clip(np.rint(item.samples * 32767), -32768, 32767).astype(np.int16)
        clock = SampleClock(origin_ns, self.format.sample_rate_hz)
        self.items += 1
        number = self.items
        self.info["playing"] = {"name": item.name, "item": number, "start_ns": origin_ns,
                                "end_ns": clock.time_at(len(pcm))}
        parts = sounding(pcm, self.format.sample_rate_hz)
        names = part_names(item, parts, self.format.sample_rate_hz)
        for part, (first, last) in enumerate(parts):
            self._report(number, part, names[part], clock.time_at(first), clock.time_at(last), stopped=False)
        self.context.poke()  # a heartbeat with playing
        log.info("playing name=%r seconds=%.2f start_ns=%d", item.name, len(pcm) / self.format.sample_rate_hz,
                 origin_ns)
        for first in range(0, len(pcm), self.chunk_frames):
            if self._cut.is_set() or self.stopping:
                sink.drop()
                now_ns = clock.time_at(clock.frames)
                self.publish(self.settings.topic, b"", now_ns, now_ns, segmentation_ended=True)
                for part, (first, last) in enumerate(parts):
                    if last > clock.frames:  # not played to its end: its real end, or none if not begun
                        self._report(number, part, names[part], clock.time_at(min(first, clock.frames)), now_ns,
                                     stopped=True)
                log.info("stopped name=%r after %.2f s", item.name, clock.frames / self.format.sample_rate_hz)
                break
            part = pcm[first:first + self.chunk_frames]
            if self._gain != 1.0:  # ducked: what is played (and published as the reference) is lower
                part = np.rint(part * self._gain).astype(np.int16)
            start_ns, end_ns = clock.advance(len(part))
            if not sink.paced and not self.settings.fast:  # a file: written just before it is played
                ahead_ns = start_ns - round(self.settings.ahead_ms * 1e6) - self.clock_ns()
                if ahead_ns > 0:
                    self.sleep_until(time.monotonic() + ahead_ns / 1e9)
            sink.write(part)
            self.publish(self.settings.topic, part, start_ns, end_ns, segmentation_ended=clock.frames >= len(pcm))
        self.played += 1
        self.info["playing"] = None
        self.context.poke()  # the heartbeat says it stopped playing

    def teardown(self) -> None:
        if self.sink is not None:
            self.sink.close()

    def _report(self, number: int, part: int, name: str, start_ns: int, end_ns: int, *, stopped: bool) -> None:
        """A playback result: when a part of an item plays (or played, if ``stopped``)."""
        self.emit(PLAYBACK, (start_ns, end_ns), generic=playback(name, number, stopped, part))


def read_transcript(path: Path) -> list[tuple[float, str]]:
    """A transcript file: a JSON list of {"start_s": number, "text": string}; SetupError if it is not one."""
    try:
        entries = json.loads(path.read_text())
        return [(float(e["start_s"]), str(e["text"])) for e in entries]
    except OSError as exc:
        raise SetupError(f"cannot read the transcript {path}: {exc.strerror}") from None
    except (ValueError, TypeError, KeyError) as exc:
        raise SetupError(f"{path} is not a transcript (a JSON list of {{\"start_s\", \"text\"}}): {exc}") from None


def part_names(item: Item, parts: list[tuple[int, int]], rate_hz: int) -> list[str]:
    """Each part's name: "say: " and the texts of the item's transcript starting in it (from 0.3 s before it
    sounds), or the item's name."""
    names = []
    for first, last in parts:
        texts = [text for start_s, text in item.said if first / rate_hz - 0.3 <= start_s < last / rate_hz]
        names.append(f"say: {' '.join(texts)}" if texts else item.name)
    return names


def sounding(pcm: np.ndarray, rate_hz: int) -> list[tuple[int, int]]:
    """The parts of ``pcm`` that sound, as (first, end) frames: 20 ms frames above SILENT_DBFS, pauses
    shorter than PAUSE_S bridged."""
    hop = max(1, rate_hz // 50)
    count = len(pcm) // hop + (len(pcm) % hop > 0)
    frames = np.zeros(count * hop)
    frames[:len(pcm)] = pcm / 32768.0
    level = 10 * np.log10(np.mean(frames.reshape(count, hop) ** 2, axis=1) + 1e-20)
    parts: list[tuple[int, int]] = []
    for index in np.flatnonzero(level > SILENT_DBFS):
        first, end = int(index) * hop, min(len(pcm), (int(index) + 1) * hop)
        if parts and first - parts[-1][1] < PAUSE_S * rate_hz:
            parts[-1] = (parts[-1][0], end)
        else:
            parts.append((first, end))
    return parts

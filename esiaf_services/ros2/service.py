"""The ros2 service's loop: follows the orchestrator's fused results (websocket /ws/fused) and publishes
them over DDS as a ROS 2 node would (esiaf_services/ros2/voices.py says what goes where), with the
tracked voices every ``tracked_period_s``. docs/ros2.md describes the topics."""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlencode

from pydantic import Field
from websockets.exceptions import WebSocketException

from esiaf.argparsing import OneLineParser
from esiaf.auth import TokenError, token
from esiaf.control import RegistrationError
from esiaf.processor import SetupError
from esiaf.runner import configure_logging, parse_set, refuse_start, settings_help
from esiaf.settings import ComponentSettings, SettingsError, load_settings

if TYPE_CHECKING:
    from esiaf.tools.feed import FusedFeed
    from esiaf_services.ros2.audio import AudioBuffer
    from esiaf_services.ros2.voices import Utterance

log = logging.getLogger(__name__)

ROS_DOMAIN_ID = "ROS_DOMAIN_ID"
MAX_DOMAIN_ID = 232  # DDS: the port of domain d is 7400 + 250 d, under 65536
LOG_EVERY = 100  # a refusal reason is logged the first time and every 100th
CONNECT_RETRY_S = 0.5  # at start-up, the orchestrator's websocket is tried again this often
AUDIO_POLL_S = 0.01  # while an utterance waits for its audio, the websocket loop wakes this often


class Ros2Settings(ComponentSettings):
    # the DDS domain; -1: ROS_DOMAIN_ID from the environment, or 0 (ROS 2's default)
    domain_id: int = Field(default=-1, ge=-1, le=MAX_DOMAIN_ID)
    # the stream to follow; "": every stream of the orchestrator
    stream: str = ""
    # every topic under this namespace (e.g. /robot1); "": /humans/... as REP-155 names them
    namespace: str = ""
    # each stream's topics under a namespace of its own, its stream id (/<stream>/humans/...)
    namespace_per_stream: bool = False
    language: str = "en-US"  # LiveSpeech.language: the recogniser's language (IETF code)
    frame_id: str = "esiaf_array"  # the frame of /humans/voices/<id>/direction: the microphone array's
    tracked_period_s: float = Field(default=1.0, gt=0)  # /humans/voices/tracked republished this often
    forget_after_s: float = Field(default=30.0, gt=0)  # a voice unheard this long leaves the tracked list
    max_voices: int = Field(default=64, ge=1)  # voices remembered at most (least recently heard forgotten)
    # the audio cut per utterance for /humans/voices/<id>/audio (esiaf run --ros2: beamformer/audio when
    # it beamforms); "": no audio topics, and the bridge needs only the websocket (no ZeroMQ, no registration)
    audio_topic: str = ""
    audio_sample_rate_hz: int = Field(default=16000, ge=8000, le=48000)  # of the audio published (mono int16)
    audio_keep_s: float = Field(default=30.0, gt=0, le=600)  # capture seconds of audio kept per stream
    # a fused result's audio waits at most this long for the audio of its whole span, then goes with what came
    audio_wait_s: float = Field(default=2.0, ge=0)
    max_pending_audio: int = Field(default=64, ge=1)  # utterances waiting for their audio at most (oldest go first)


def domain_id(settings: Ros2Settings, env: dict[str, str] | os._Environ[str]) -> int:
    """The setting, else ROS_DOMAIN_ID as ROS 2 reads it (an integer 0..232; unset or empty: 0)."""
    if settings.domain_id >= 0:
        return settings.domain_id
    text = env.get(ROS_DOMAIN_ID, "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) > MAX_DOMAIN_ID:
        raise SettingsError(f"{ROS_DOMAIN_ID}={text!r}: not a DDS domain id (an integer 0..{MAX_DOMAIN_ID})")
    return int(text)


def feed_url(settings: Ros2Settings) -> str:
    base = settings.orchestrator_url.rstrip("/").replace("http://", "ws://", 1).replace("https://", "wss://", 1)
    query = ({"stream": settings.stream} if settings.stream else {}) | {"partials": 1}  # incremental speech
    return f"{base}/ws/fused?{urlencode(query)}"


class Ros2:
    """ESIAF's voices as ROS4HRI topics (REP-155) over Cyclone DDS, from the orchestrator's fused results."""

    service = "ros2"
    Settings = Ros2Settings

    def __init__(self, settings: Ros2Settings, domain: int) -> None:
        from esiaf_services.ros2.dds import Writers
        from esiaf_services.ros2.voices import Voices, namespace
        self.settings, self.domain = settings, domain
        self.voices = Voices(prefix=namespace(settings.namespace), per_stream=settings.namespace_per_stream,
                             language=settings.language, frame_id=settings.frame_id,
                             forget_after_s=settings.forget_after_s, max_voices=settings.max_voices)
        self.writers = Writers(domain)
        self.refused: Counter[str] = Counter()
        self.published = 0
        self.audio: AudioBuffer | None = None
        if settings.audio_topic:
            from esiaf_services.ros2.audio import AudioBuffer
            self.audio = AudioBuffer(settings.audio_sample_rate_hz, settings.audio_keep_s, settings.max_streams)
        self.pending: deque[tuple[Utterance, float]] = deque()  # (utterance, monotonic deadline), oldest first

    def handle(self, text: str | bytes, now_s: float) -> None:
        """One websocket message: published, or counted and logged (never raised)."""
        from esiaf_services.ros2.voices import Unmappable
        try:
            message = json.loads(text)
            if not isinstance(message, dict):
                raise Unmappable("not_an_object", type(message).__name__)
            kind = message.get("type")
            utterance = None
            if kind == "fused_result":
                publications = self.voices.fused(message, now_s)
                utterance = self.voices.utterance(message) if self.audio is not None else None
            elif kind == "partial":
                publications = self.voices.partial(message, now_s)
            elif kind == "stream_end":
                return
            else:
                raise Unmappable("unknown_type", repr(kind)[:80])
        except json.JSONDecodeError as exc:
            self.refuse("not_json", str(exc))
            return
        except Unmappable as exc:
            self.refuse(exc.reason, str(exc))
            return
        self.publish(publications)
        self.want_audio(utterance, now_s)

    def publish(self, publications: list[tuple[str, Any]]) -> None:
        from cyclonedds.core import DDSException
        for topic, sample in publications:
            try:
                self.writers.write(topic, sample)
            except DDSException as exc:  # a topic DDS refuses (a name too long, ...): that one is lost
                self.refuse("dds_refused", f"{topic}: {exc}")
                continue
            self.published += 1

    def want_audio(self, utterance: Utterance | None, now_s: float) -> None:
        """An utterance's audio, published once the audio topic has reached its end (or ``audio_wait_s``
        has passed); the oldest waiting goes unpublished past ``max_pending_audio``."""
        if utterance is None:
            return
        if len(self.pending) >= self.settings.max_pending_audio:
            dropped, _ = self.pending.popleft()
            self.refuse("audio_pending_full", f"{dropped.topic}: more than {self.settings.max_pending_audio} waiting")
        self.pending.append((utterance, now_s + self.settings.audio_wait_s))
        self.publish_audio(now_s)

    def publish_audio(self, now_s: float) -> None:
        """The waiting utterances whose audio is all there, or whose wait is over, in the order they came."""
        from esiaf_services.ros2.messages import AudioData
        assert self.audio is not None
        while self.pending:
            utterance, deadline = self.pending[0]
            if self.audio.reached_ns(utterance.stream_id) < utterance.end_ns and now_s < deadline:
                return
            self.pending.popleft()
            pcm = self.audio.cut(utterance.stream_id, utterance.start_ns, utterance.end_ns)
            if not pcm:
                self.refuse("no_audio", f"{utterance.topic}: no audio of {utterance.stream_id} kept for "
                            f"{utterance.start_ns}..{utterance.end_ns} on {self.settings.audio_topic}")
                continue
            self.publish([(utterance.topic, AudioData(data=pcm))])

    def refuse(self, reason: str, detail: str) -> None:
        self.refused[reason] += 1
        count = self.refused[reason]
        if count == 1 or count % LOG_EVERY == 0:
            log.warning("refused a websocket message reason=%s count=%d: %s", reason, count, detail[:200])

    def tick(self) -> None:
        self.publish(self.voices.tracked(time.monotonic(), time.time_ns()))
        if self.settings.health_file:
            Path(self.settings.health_file).touch()

    def connect(self) -> FusedFeed:
        """The websocket, tried until ``register_timeout_s`` has passed (the orchestrator may start later)."""
        from esiaf.tools.feed import FusedFeed
        deadline = time.monotonic() + self.settings.register_timeout_s
        while True:
            try:
                return FusedFeed(feed_url(self.settings))
            except (OSError, TimeoutError, WebSocketException):
                if time.monotonic() >= deadline:
                    raise
                time.sleep(CONNECT_RETRY_S)

    def run(self) -> int:
        """Follows the fused results; with an audio topic, in a thread beside the SDK consumer that
        hears the audio (registered with the orchestrator as the ``ros2`` service, in this thread: it
        owns the signals), until either stops."""
        if self.audio is None:
            self.follow(threading.Event())
            return 0
        from esiaf_services.ros2.audio import VoiceAudio
        consumer = VoiceAudio(self.settings, self.settings.audio_topic, self.audio)
        stopped = threading.Event()
        failed: list[BaseException] = []

        def follow() -> None:
            try:
                self.follow(stopped)
            except (OSError, TimeoutError, WebSocketException) as exc:
                failed.append(exc)
                consumer.stop(2)

        follower = threading.Thread(target=follow, name="ros2-fused", daemon=True)
        follower.start()
        try:
            code = consumer.run()
        finally:
            stopped.set()
            follower.join(timeout=5)
        if failed:
            raise failed[0]
        return code

    def follow(self, stopped: threading.Event) -> None:
        log.info("following %s, publishing on DDS domain %d", feed_url(self.settings), self.domain)
        with self.connect() as feed:
            next_tick = time.monotonic()
            while not stopped.is_set():
                now = time.monotonic()
                if now >= next_tick:
                    self.tick()
                    next_tick = max(next_tick + self.settings.tracked_period_s, now)
                if self.pending:
                    self.publish_audio(now)
                wait_s = next_tick - time.monotonic()
                try:
                    text = feed.recv(timeout=max(min(wait_s, AUDIO_POLL_S) if self.pending else wait_s, 0.001))
                except TimeoutError:
                    continue
                self.handle(text, time.monotonic())


def main(component_cls: type[Ros2], argv: Sequence[str] | None = None) -> int:
    service = component_cls.service
    parser = OneLineParser(prog=f"python -m esiaf_services.{service}", description=component_cls.__doc__,
                           epilog=settings_help(component_cls.Settings, service),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help=f"YAML settings file (also ESIAF_{service.upper()}_CONFIG)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one setting (repeatable; the value is read as YAML)")
    args = parser.parse_args(argv)
    try:
        settings = load_settings(component_cls.Settings, service, config=args.config, **parse_set(args.set))
        domain = domain_id(settings, os.environ)
        token()
    except (SettingsError, TokenError) as exc:
        return refuse_start(service, exc)
    configure_logging(service, settings.log_level)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(0))  # stopped as asked: say what was done
    try:
        bridge = component_cls(settings, domain)
    except ImportError as exc:
        return refuse_start(service, f"{exc.name or exc}: not installed (pip install 'esiaf[ros2]')")
    try:
        return bridge.run()
    except (SetupError, RegistrationError) as exc:
        return refuse_start(service, exc)
    except (OSError, TimeoutError, WebSocketException) as exc:
        return refuse_start(service, f"the orchestrator's websocket {feed_url(settings)}: {exc or type(exc).__name__}")
    except KeyboardInterrupt:
        return 130
    finally:
        log.info("published=%d refused=%s", bridge.published, dict(bridge.refused) or 0)

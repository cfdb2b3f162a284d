"""The component base class: what every ESIAF service is built on.

A component declares audio inputs and outputs (topic + the format it wants), loads what it needs
in :meth:`Component.setup` (which may fail cleanly), and handles one message at a time. The SDK
owns the sockets and the loop, registration and heartbeats, sequence numbers and loss counting,
capture timestamps, format conversion between the declared formats and the ones the orchestrator
assigns to the topics (esiaf/links.py), the callback order (audio, then SSL meta, then VAD end,
then end of stream) and shutdown on SIGTERM/SIGINT.

All handlers run on one thread, in order; the heartbeat on another, so a long computation does not
make the component look dead (a native call holding the GIL must say so: ControlClient.quiet_for).
The input side (bounds on what peers send, loss counting, per-publisher conversion): esiaf/receiving.py.
"""
from __future__ import annotations

import json
import logging
import math
import socket
import threading
import time
import uuid
from collections.abc import Iterable
from dataclasses import asdict
from typing import Any, ClassVar

import numpy as np
import zmq

from esiaf import binding, keys, per_stream, signals
from esiaf.api_client import announce_stream
from esiaf.audio import Audio
from esiaf.control import ControlClient
from esiaf.formats import AudioFormat, encode
from esiaf.links import OutputLink, OutputStats
from esiaf.proto import esiaf_pb2 as pb
from esiaf.receiving import InputStats, Receiver
from esiaf.results import make_result
from esiaf.settings import ComponentSettings
from esiaf.transport import Transport, TransportError, topic_name

log = logging.getLogger(__name__)

IDLE_WAIT_MS = 5_000  # a consumer's longest sleep in one poll (input, control and stop() wake it)


class SetupError(Exception):
    """A component could not be configured (model missing, device unknown...)."""


class Component:
    """Subclass it, set ``service`` and ``designation``, declare topics, override handlers."""

    service: ClassVar[str] = "component"
    designation: ClassVar[str] = "other"  # result type produced, or "other"
    Settings: ClassVar[type[ComponentSettings]] = ComponentSettings
    options: ClassVar[dict[str, str]] = {}  # settings that get a command-line flag: name -> help

    def __init__(self, settings: ComponentSettings):
        self.settings = settings
        self.inputs: dict[str, AudioFormat] = {}
        self.outputs: dict[str, AudioFormat] = {}
        # this instance of its service (the name): unique while it lives, ours unless set
        self.instance_id = settings.instance or f"{settings.name}-{uuid.uuid4().hex[:8]}"
        self._incarnation = uuid.uuid4().hex  # this process: its own registrations replace each other
        self.output_stats: dict[str, OutputStats] = {}
        self.info: dict[str, Any] = {}  # reported with every heartbeat
        self.results_sent = 0
        self.results_dropped = 0
        self._stop = threading.Event()
        self._exit_code = 0
        self._sequences: dict[tuple[str, str], int] = {}  # per topic and stream: a replica sees its streams only
        self.refused_subscribers: dict[str, int] = {}  # handshakes refused at the outputs (CURVE), by reason
        self._ended = per_stream.PerStream(lambda _: set[str](), settings.max_streams, "inputs ended", info=self.info)
        self._result_sequence = 0
        self._handling = False  # inside a handler: audio input waits, so handlers never nest
        self._assigned: dict[str, AudioFormat] = {}
        self._output_links: dict[str, OutputLink] = {}  # made in run(): setup() may still declare topics
        self._context: zmq.Context | None = None
        self._transport: Transport | None = None
        self.control: ControlClient | None = None
        # the input side (esiaf/receiving.py); its counters and state, under their names of old too
        self._receiver = Receiver(self.inputs, on_loss=self._poke_control)
        self.input_stats = self._receiver.stats
        self.refused = self._receiver.refused  # audio messages refused, by reason
        self.refused_by_publisher = self._receiver.refused_by_publisher  # ... by publisher (the most recent ones)

    @property
    def _wire(self) -> Transport:  # the sockets: made by run() before it registers, closed when it returns
        if self._transport is None:
            raise RuntimeError(f"{type(self).__name__}: the sockets are used before run() made them")
        return self._transport

    # -- declaration -----------------------------------------------------------------
    def add_input(self, topic: str, fmt: AudioFormat) -> None:
        self.inputs[topic] = fmt
        self.input_stats[topic] = InputStats()

    def add_output(self, topic: str, fmt: AudioFormat) -> None:
        self.outputs[topic] = fmt
        self.output_stats[topic] = OutputStats()

    # -- hooks to override -----------------------------------------------------------
    def setup(self) -> None:
        """Load models, open devices. Raise SetupError with a clear message on failure."""

    def on_audio(self, audio: Audio) -> None:
        """Every received chunk, first."""

    def on_ssl(self, audio: Audio) -> None:
        """A chunk that carries SSL directions, after on_audio."""

    def on_segment_end(self, audio: Audio) -> None:
        """The last chunk of an utterance, after on_audio and on_ssl."""

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """Every input has ended ``stream_id``. By default, end it on every output too."""
        for topic in self.outputs:
            self.publish(topic, b"", audio.end_ns, audio.end_ns, stream_id=stream_id, end_of_stream=True)

    def produce(self) -> None:
        """Sources override this with their capture loop; consumers leave it alone."""
        raise NotImplementedError

    def teardown(self) -> None:
        """Release what setup took."""

    # -- actions ---------------------------------------------------------------------
    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self, exit_code: int = 0) -> None:
        self._exit_code = self._exit_code or exit_code
        self._stop.set()
        if self._transport is not None:
            self._transport.stop()  # a long wait for input, or a replay's for a consumer, ends now

    def publish(self, topic: str, audio: bytes | np.ndarray, start_ns: int, end_ns: int, *,
                stream_id: str | None = None, segmentation_ended: bool = False,
                segment: tuple[int, int] | None = None, ssl_directions: Iterable[pb.SslDirection] = (),
                end_of_stream: bool = False) -> int:
        """Publishes a chunk on an output topic; returns its sequence number (0 if dropped).

        ``audio`` is in the format declared with :meth:`add_output`; the SDK converts it to the
        topic's assigned format. A chunk marked ``segmentation_ended`` or ``end_of_stream`` also
        carries what the resampler held back, so consumers have all audio before the mark.
        """
        link = self._output_links[topic]
        payload = audio if isinstance(audio, (bytes, bytearray, memoryview)) else encode(audio, link.declared)
        stream_id = stream_id or self.settings.stream_id
        sequence = 0
        for out in link.messages(payload, start_ns, end_ns, stream_id, segmentation_ended, end_of_stream):
            msg = pb.AugmentedAudio(stream_id=out.stream_id, topic=topic, format=out.format.to_proto(),
                                    start_ns=out.chunk.start_ns, end_ns=out.chunk.end_ns, payload=out.chunk.payload)
            if out.main:
                msg.meta.segmentation_ended = segmentation_ended
                msg.meta.end_of_stream = end_of_stream
                if segment is not None:
                    msg.meta.segment.start_ns, msg.meta.segment.end_ns = segment
                msg.meta.ssl_directions.extend(ssl_directions)
            sequence = self._send_audio(topic, msg)
        return sequence

    def _send_audio(self, topic: str, msg: pb.AugmentedAudio) -> int:
        key = (topic, msg.stream_id)
        sequence = self._sequences.get(key, 0) + 1
        msg.publisher, msg.sequence = self.instance_id, sequence
        stats = self.output_stats[topic]
        sent, frames = self._wire.send_audio(topic, msg)  # a replay's waits for the consumers (esiaf/transport.py)
        self._hand_on(frames)
        if not sent:
            stats.dropped += 1
            log.warning("audio dropped at high-water mark topic=%s sequence=%d dropped=%d",
                        topic, sequence, stats.dropped)
            return 0
        self._sequences[key] = sequence
        stats.published += 1
        if not self._handling:  # a producer; a handler's caller services the sockets when it returns
            self._service(0)
        return sequence

    def _hand_on(self, frames: list[bytes]) -> None:
        """An audio message received or published, as on the wire: a host's guests take it (esiaf/hosting.py)."""

    def forward(self, topic: str, audio: Audio, **meta: Any) -> int:
        """Publishes a received chunk (same capture times) on an output topic; its payload, in the
        input's declared format, must be in the output's declared format too."""
        return self.publish(topic, audio.payload, audio.start_ns, audio.end_ns, stream_id=audio.stream_id, **meta)

    def emit(self, result_type: str, span: tuple[int, int], *, stream_id: str | None = None,
             **payload: Any) -> pb.Result:
        """Sends a result to the orchestrator. ``payload`` is one of vad=, speech=, ssl=, ..., nothing=."""
        self._result_sequence += 1
        result = make_result(self.settings.name, result_type, stream_id or self.settings.stream_id, span,
                             self._result_sequence, **payload)
        result.instance = self.instance_id
        self._send_results(b"result", result.SerializeToString(), result.stream_id)
        return result

    def clock_ns(self) -> int:  # this host's wall clock, ns since the epoch: what capture times are stamped with
        return time.time_ns() + round(self.settings.clock_skew_s * 1e9)

    def announce_stream(self, start_ns: int, stream_id: str | None = None, **info: Any) -> None:
        """Sources call this when capture starts (the orchestrator records it); not ``realtime``: a replay."""
        stream_id = stream_id or self.settings.stream_id
        self._receiver.replays.note(stream_id, info.get("realtime") is False)
        announce_stream(self.settings.orchestrator_url, stream_id, start_ns, self.instance_id, info)

    def wait_for_subscribers(self, topic: str, count: int, timeout_s: float) -> bool:
        """Services the sockets until ``topic`` has ``count`` subscribers, or the time is up."""
        deadline = time.monotonic() + timeout_s
        while self.subscribers(topic) < count:
            if self.stopping or time.monotonic() >= deadline:
                return False
            self._service(max(1, int((deadline - time.monotonic()) * 1000)))  # a subscription wakes it
        return True

    def subscribers(self, topic: str) -> int:  # of an output topic (a host's guests' too: esiaf/hosting.py)
        return self.output_stats[topic].subscribers

    def sleep_until(self, deadline_monotonic: float) -> None:
        """Waits (servicing sockets) until a monotonic time, or until stopped: up to 1 ms past it, as
        zmq polls in whole milliseconds (rounded up: one wake-up per wait, not a poll and a sleep)."""
        while not self.stopping:
            remaining_ms = (deadline_monotonic - time.monotonic()) * 1000
            if remaining_ms <= 0:
                return
            self._service(math.ceil(remaining_ms))

    # -- running ---------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """What the heartbeat carries; each input's ``queued`` starts again for the next one."""
        return {"inputs": {t: s.heartbeat() for t, s in list(self.input_stats.items())},
                "outputs": {t: asdict(s) for t, s in list(self.output_stats.items())},
                "results_sent": self.results_sent, "results_dropped": self.results_dropped,
                "refused": dict(self.refused), "refused_by_publisher": dict(self.refused_by_publisher),
                "refused_subscribers": dict(self.refused_subscribers),
                "info": dict(self.info)}

    def run(self) -> int:
        """Set up, register, process until stopped; returns the exit code."""
        signals.install(self.stop, lambda: self._transport.reload_keys_soon() if self._transport else None)
        try:  # before setup(): a bad key file fails at once, not after a model has loaded
            curve = keys.load(orchestrator=False)
        except keys.KeyFileError as exc:
            raise SetupError(str(exc)) from None
        self.setup()
        self._context = zmq.Context()
        try:
            try:
                self._transport = Transport(self._context, inputs=self.inputs, has_outputs=bool(self.outputs),
                                            bind_host=self.settings.bind_host, audio_port=self.settings.audio_port,
                                            advertise_host=self.settings.advertise_host, curve=curve,
                                            audio_queue=self.settings.audio_queue, replays=self._receiver.replays)
            except TransportError as exc:
                raise SetupError(str(exc)) from None
            self.control = ControlClient(self._context, self.settings.orchestrator_url,
                                         self._registration_request(), self.stats,
                                         self.settings.register_timeout_s, self.settings.health_file, curve,
                                         self.clock_ns)
            self._output_links = {t: OutputLink(t, f) for t, f in self.outputs.items()}
            self._wire.on_busy = self.control.busy  # audio or results moving: the heartbeat stays fast
            registration = self.control.start()
            self._apply_state(registration.state())
            if type(self).produce is not Component.produce:
                self.produce()
            else:  # a consumer: sleeps until input, a control message or stop() wakes it
                while not self.stopping:
                    self._service(IDLE_WAIT_MS)
        finally:
            self._shutdown()
        return self._exit_code

    def _registration_request(self) -> dict[str, Any]:
        def topics(declared: dict[str, AudioFormat]) -> list[dict[str, Any]]:
            return [{"topic": t, "format": f.to_dict()} for t, f in declared.items()]
        return {"name": self.settings.name, "instance": self.instance_id, "incarnation": self._incarnation,
                "designation": self.designation, "stream_id": self.settings.stream_id,
                "inputs": topics(self.inputs), "outputs": topics(self.outputs),
                "audio_endpoint": self._wire.audio_endpoint, "host": socket.gethostname(), "info": self.info,
                **({"audio_public_key": key} if (key := self._wire.audio_public_key) else {})}

    def _service(self, timeout_ms: float) -> None:
        """Handles whatever is ready on the sockets, waiting up to ``timeout_ms`` for the first.

        Called from inside a handler (publish() does), it takes no audio input: the next chunk
        waits until the current handler has returned, so callbacks never nest or reorder.
        """
        taken: dict[bytes, int] = {}  # audio messages taken back to back, by topic frame: its queue
        for kind, event in self._wire.events(timeout_ms, take_audio=not self._handling):
            if self.stopping and kind == "audio":
                break  # SIGTERM while a backlog drains: stop now, not after the backlog
            if kind == "state":
                self._apply_state(event)
            elif kind == "subscription":
                self._on_subscription(*event)
            elif kind == "refused":
                self._refuse_subscriber(event)
            else:
                if event:
                    taken[event[0]] = taken.get(event[0], 0) + 1
                self._on_message(event)
        for frame, count in taken.items():
            if (stats := self.input_stats.get(topic_name(frame))) is not None:
                stats.took_back_to_back(count)

    def _apply_state(self, state: dict[str, Any]) -> None:
        if state.get("type") == "fatal":
            log.error("stopping: %s", state.get("error"))
            self.stop(exit_code=1)
            return
        self._wire.connect_peers({e for endpoints in state.get("peers", {}).values() for e in endpoints},
                                      state.get("peer_keys", {}))
        self._wire.connect_results(state.get("results_endpoint", ""))
        self._wire.take_streams(state.get("streams"))
        for topic, fmt in state.get("formats", {}).items():
            assigned = AudioFormat.from_dict(fmt)
            if self._assigned.get(topic) == assigned:
                continue
            self._assigned[topic] = assigned
            declared = self.outputs.get(topic) or self.inputs.get(topic)
            log.info("format assigned topic=%s wire=%s declared=%s%s", topic, assigned, declared,
                     "" if assigned == declared else " (converted here)")
            if topic in self._output_links:
                self._output_links[topic].assigned = assigned  # the switch happens at the next chunk

    def _refuse_subscriber(self, reason: str) -> None:
        count = self.refused_subscribers[reason] = self.refused_subscribers.get(reason, 0) + 1
        if count == 1 or count % 100 == 0:
            log.warning("refused a subscriber's handshake reason=%s count=%d", reason, count)

    def _on_subscription(self, topic: str, change: int) -> None:
        stats = self.output_stats.get(topic)
        if stats is None:
            return
        stats.subscribers = max(0, stats.subscribers + change)
        log.info("subscribers topic=%s count=%d", topic, stats.subscribers)
        self._poke_control()

    def _poke_control(self) -> None:
        """A heartbeat now, if registered: something worth reporting changed."""
        if self.control is not None:
            self.control.poke()

    def _on_message(self, frames: list[bytes]) -> None:
        received = self._receiver.receive(frames)
        if received is None:
            return  # refused (counted and logged), or a topic this component did not subscribe to
        self._handling = True
        try:
            for chunk in received.chunks:
                self._dispatch(chunk)
        except Exception:  # a handler bug must not kill the component: count, log, go on
            received.stats.bad += 1
            audio = received.audio
            log.exception("handler failed topic=%s sequence=%d start_ns=%d", received.topic, audio.sequence,
                          audio.start_ns)
        finally:
            self._handling = False

    def _dispatch(self, audio: Audio) -> None:
        self.on_audio(audio)
        if audio.meta.ssl_directions:
            self.on_ssl(audio)
        if audio.meta.segmentation_ended:
            self.on_segment_end(audio)
        if audio.meta.end_of_stream:
            self._on_input_ended(audio)

    def _on_input_ended(self, audio: Audio) -> None:
        ended = self._ended.get(audio.stream_id)
        ended.add(audio.topic)
        if ended != set(self.inputs):
            return
        self._ended.pop(audio.stream_id)
        self.on_end_of_stream(audio.stream_id, audio)
        notice = {"component_id": self.control.component_id if self.control else "",
                  "component": self.settings.name, "stream_id": audio.stream_id}
        self._send_results(b"end_of_stream", json.dumps(notice).encode(), audio.stream_id)
        log.info("end of stream stream_id=%s", audio.stream_id)

    def _send_results(self, kind: bytes, body: bytes, stream_id: str) -> None:  # signed: esiaf/binding.py
        registration = self.control.registration if self.control else None
        if self._wire.send_results(binding.signed(kind, body, registration), stream_id):  # a replay's wait
            self.results_sent += kind == b"result"
        else:
            self.results_dropped += 1
            log.error("result dropped: orchestrator not taking results dropped=%d", self.results_dropped)

    def _shutdown(self) -> None:
        try:
            self.teardown()
        finally:
            if self.control is not None:
                self.control.stop()
            if self._transport is not None:
                self._transport.close()
            if self._context is not None:
                self._context.term()

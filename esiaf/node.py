"""The node: the runtime that runs processors (esiaf/processor.py) in one process over ZeroMQ.

A node owns the sockets (esiaf/transport.py) and the loop, installs the signals, and shuts down on
SIGTERM/SIGINT. Each processor it runs gets a :class:`Context`: its own registration and heartbeat
thread (esiaf/control.py), its input side (bounds on what peers send, loss counting, per-publisher
conversion: esiaf/receiving.py), its output links (conversion to the topics' assigned formats,
esiaf/links.py), sequence numbers, results and end-of-stream notices, and the callback order (audio,
then SSL meta, then VAD end, then end of stream).

All handlers run on one thread, in order; the heartbeats on others, so a long computation does not
make the component look dead (a native call holding the GIL must say so: ControlClient.quiet_for).

A node with several processors runs the first as its *primary* (its sockets are the ones it
registers and subscribes for) and the others alongside it (the ``guests`` setting: the grabber
hosting the vad, emotion hosting gender). Each still registers as its own service with its own
instance id, result kind, heartbeats and results; the others register the primary's audio
endpoint as theirs, so a consumer of their output topics subscribes to it at the primary's socket,
which counts a subscription to a processor's topic as that processor's. Every audio message the
node receives, and every message a processor publishes, reaches the processors after it that take
its topic, as it would arrive over the wire (their own conversion and counters): no ZeroMQ hop
and no second process woken per chunk. A processor hosted so is not scaled apart from the primary
(``--replicas`` runs the analysers apart), and an exception in its handlers is counted on its input
(``bad``) and logged, and the node goes on.
"""
from __future__ import annotations

import json
import logging
import math
import queue
import socket
import threading
import time
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
import zmq

from esiaf import binding, keys, per_stream, signals
from esiaf.api_client import announce_stream
from esiaf.audio import Audio
from esiaf.control import ControlClient
from esiaf.control_messages import Command, Fatal, LocalState, parse_to_data_thread
from esiaf.formats import AudioFormat, encode
from esiaf.links import OutputLink, OutputStats
from esiaf.processor import Processor, SetupError
from esiaf.proto import esiaf_pb2 as pb
from esiaf.receiving import InputStats, Receiver
from esiaf.result_checks import MAX_RESULT_BYTES, BadResult, check_result
from esiaf.results import make_result
from esiaf.transport import STATE_ADDRESS, Transport, TransportError, topic_name

log = logging.getLogger(__name__)

IDLE_WAIT_MS = 5_000  # a consumer's longest sleep in one poll (input, control and stop() wake it)


class Context:
    """One processor's runtime: what it publishes and emits through, and its own counters."""

    def __init__(self, processor: Processor):
        self.processor = processor
        self.node: Node | None = None  # the node running it: set when one does
        self.stop_asked: int | None = None  # stop() before a node ran it: the exit code asked for
        settings = processor.settings
        self.settings = settings
        self.incarnation = uuid.uuid4().hex  # this process: its own registrations replace each other
        self.output_stats: dict[str, OutputStats] = {}
        self.results_sent = 0
        self.results_dropped = 0
        self.results_invalid = 0  # results it made that the orchestrator would refuse: never sent
        self.results_invalid_reason = ""  # the last one's
        self.refused_subscribers: dict[str, int] = {}  # handshakes refused at the outputs (CURVE), by reason
        self.sequences: dict[tuple[str, str], int] = {}  # per topic and stream: a replica sees its streams only
        self.ended = per_stream.PerStream(lambda _: set[str](), settings.max_streams, "inputs ended",
                                          info=processor.info)
        self.result_sequence = 0
        self.handling = False  # inside one of its handlers
        self.assigned: dict[str, AudioFormat] = {}
        self.output_links: dict[str, OutputLink] = {}  # made by the node: setup() may still declare topics
        self.control: ControlClient | None = None
        self.receiver = Receiver(processor.inputs, on_loss=self.poke)
        self.input_stats = self.receiver.stats
        self.refused = self.receiver.refused  # audio messages refused, by reason
        self.refused_by_publisher = self.receiver.refused_by_publisher  # ... by publisher (the most recent ones)
        self.declared()
        # a hosted processor's state from the orchestrator (formats), applied on the data thread
        self._formats: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()
        self._commands: queue.SimpleQueue[Command] = queue.SimpleQueue()  # a guest's, until its next message
        self._zmq: zmq.Context | None = None  # a hosted processor's: its control thread's state socket
        self._state_thread: threading.Thread | None = None
        self._transport: Transport | None = None  # hosted: the node's sockets, whose output its consumers may take

    def declared(self) -> None:
        """Counters for every declared topic (a processor may declare topics until it runs)."""
        for topic in self.processor.inputs:
            self.input_stats.setdefault(topic, InputStats())
        for topic in self.processor.outputs:
            self.output_stats.setdefault(topic, OutputStats())

    @property
    def _node(self) -> Node:
        if self.node is None:
            raise RuntimeError(f"{type(self.processor).__name__}: the sockets are used before run() made them")
        return self.node

    # -- what a processor does through it ----------------------------------------------
    @property
    def stopping(self) -> bool:
        return self.node.stopping if self.node is not None else self.stop_asked is not None

    def stop(self, exit_code: int = 0) -> None:
        """Stops the node that runs it; asked before one does, the node stops as it starts."""
        if self.node is not None:
            self.node.stop(exit_code)
        else:
            self.stop_asked = self.stop_asked or exit_code

    def publish(self, topic: str, audio: bytes | np.ndarray, start_ns: int, end_ns: int, *,
                stream_id: str | None = None, segmentation_ended: bool = False,
                segment: tuple[int, int] | None = None, ssl_directions: Iterable[pb.SslDirection] = (),
                end_of_stream: bool = False, broken_off: bool = False,
                speech_until_ns: int = 0) -> int:
        """Publishes a chunk on an output topic; returns its sequence number (0 if dropped).

        ``audio`` is in the format declared with ``add_output``; the SDK converts it to the
        topic's assigned format. A chunk marked ``segmentation_ended`` or ``end_of_stream`` also
        carries what the resampler held back, so consumers have all audio before the mark.
        ``broken_off``: the utterance this component was passing on broke off before this chunk
        (``meta.broken_off``, on its first message; esiaf/receiving.py). ``speech_until_ns``: a VAD's
        open utterance was last heard speaking at this capture time (``meta.speech_until_ns``, on every
        message; 0: not known).
        """
        link = self.output_links[topic]
        payload = audio if isinstance(audio, (bytes, bytearray, memoryview)) else encode(audio, link.declared)
        stream_id = stream_id or self.settings.stream_id
        sequence = 0
        for out in link.messages(payload, start_ns, end_ns, stream_id, segmentation_ended, end_of_stream):
            msg = pb.AugmentedAudio(stream_id=out.stream_id, topic=topic, format=out.format.to_proto(),
                                    start_ns=out.chunk.start_ns, end_ns=out.chunk.end_ns, payload=out.chunk.payload)
            msg.meta.broken_off, broken_off = broken_off, False  # the first message says it
            msg.meta.speech_until_ns = speech_until_ns
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
        sequence = self.sequences.get(key, 0) + 1
        msg.publisher, msg.sequence = self.processor.instance_id, sequence
        stats = self.output_stats[topic]
        if not self._node.send_audio(self, topic, msg):
            stats.dropped += 1
            log.warning("audio dropped at high-water mark topic=%s sequence=%d dropped=%d",
                        topic, sequence, stats.dropped)
            return 0
        self.sequences[key] = sequence
        stats.published += 1
        return sequence

    def forward(self, topic: str, audio: Audio, **meta: Any) -> int:
        """Publishes a received chunk (same capture times) on an output topic; its payload, in the
        input's declared format, must be in the output's declared format too."""
        return self.publish(topic, audio.payload, audio.start_ns, audio.end_ns, stream_id=audio.stream_id, **meta)

    def emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None,
             **payload: Any) -> pb.Result:
        """Sends a result to the orchestrator. ``payload`` is one of vad=, speech=, ssl=, ..., nothing=."""
        self.result_sequence += 1
        result = make_result(self.settings.name, kind, stream_id or self.settings.stream_id, span,
                             self.result_sequence, **payload)
        result.instance = self.processor.instance_id
        body = result.SerializeToString()
        try:  # what the orchestrator would refuse is not sent: the analyser learns it here, counted
            if len(body) > MAX_RESULT_BYTES:
                raise BadResult(f"{kind} result of {len(body)} bytes, more than {MAX_RESULT_BYTES}")
            check_result(result)
        except BadResult as exc:
            self.results_invalid += 1
            self.results_invalid_reason = str(exc)[:500]
            if self.results_invalid == 1 or self.results_invalid % 100 == 0:
                log.error("result not sent: the orchestrator would refuse it (%s) invalid=%d", exc,
                          self.results_invalid)
                self.poke()
            return result
        self._send_results(b"result", body, result.stream_id)
        return result

    def clock_ns(self) -> int:  # this host's wall clock, ns since the epoch: what capture times are stamped with
        return time.time_ns() + round(self.settings.clock_skew_s * 1e9)

    def announce_stream(self, start_ns: int, stream_id: str | None = None, **info: Any) -> None:
        """Sources call this when capture starts (the orchestrator records it); not ``realtime``: a replay."""
        stream_id = stream_id or self.settings.stream_id
        self.receiver.replays.note(stream_id, info.get("realtime") is False)
        announce_stream(self.settings.orchestrator_url, stream_id, start_ns, self.processor.instance_id, info)

    def join_stream(self, stream_id: str, replay: bool) -> None:
        """A source that publishes into a stream another source announced (a robot's player beside its
        grabber): when that is a replay, its audio waits for the consumers as the stream's does."""
        self.receiver.replays.note(stream_id, replay)

    def wait_for_subscribers(self, topic: str, count: int, timeout_s: float) -> bool:
        """Services the sockets until ``topic`` has ``count`` subscribers, or the time is up."""
        deadline = time.monotonic() + timeout_s
        while self.subscribers(topic) < count:
            if self.stopping or time.monotonic() >= deadline:
                return False
            self._node.service(max(1, int((deadline - time.monotonic()) * 1000)))  # a subscription wakes it
        return True

    def subscribers(self, topic: str) -> int:
        """Of an output topic, its own or another processor's of its node (its guest's)."""
        owner = self.node.publisher_of(topic) if self.node is not None else None
        return (owner or self).output_stats[topic].subscribers

    def publishes(self, topic: str) -> bool:
        """Whether it, or another processor of its node, publishes ``topic``."""
        return topic in self.output_stats or (self.node is not None and self.node.publisher_of(topic) is not None)

    def sleep_until(self, deadline_monotonic: float) -> None:
        """Waits (servicing sockets) until a monotonic time, or until stopped: up to 1 ms past it, as
        zmq polls in whole milliseconds (rounded up: one wake-up per wait, not a poll and a sleep)."""
        while not self.stopping:
            remaining_ms = (deadline_monotonic - time.monotonic()) * 1000
            if remaining_ms <= 0:
                return
            self._node.service(math.ceil(remaining_ms))

    def stats(self) -> dict[str, Any]:
        """What the heartbeat carries; each input's ``queued`` starts again for the next one."""
        self.processor.refresh_info()
        return {"inputs": {t: s.heartbeat() for t, s in list(self.input_stats.items())},
                "outputs": {t: asdict(s) for t, s in list(self.output_stats.items())},
                "results_sent": self.results_sent, "results_dropped": self.results_dropped,
                "results_invalid": self.results_invalid, "results_invalid_reason": self.results_invalid_reason,
                "refused": dict(self.refused), "refused_by_publisher": dict(self.refused_by_publisher),
                "refused_subscribers": dict(self.refused_subscribers),
                "info": dict(self.processor.info)}

    # -- what the node does with it ------------------------------------------------------
    def poke(self) -> None:
        """A heartbeat now, if registered: something worth reporting changed."""
        if self.control is not None:
            self.control.poke()

    def registration_request(self, transport: Transport) -> dict[str, Any]:
        def topics(declared: dict[str, AudioFormat]) -> list[dict[str, Any]]:
            return [{"topic": t, "format": f.to_dict()} for t, f in declared.items()]
        processor = self.processor
        return {"name": self.settings.name, "instance": processor.instance_id, "incarnation": self.incarnation,
                "kind": processor.kind, "stream_id": self.settings.stream_id,
                "inputs": topics(processor.inputs), "outputs": topics(processor.outputs),
                "audio_endpoint": transport.audio_endpoint, "host": socket.gethostname(), "info": processor.info,
                **({"audio_public_key": key} if (key := transport.audio_public_key) else {})}

    def apply_formats(self, formats: dict[str, Any]) -> None:
        """The wire formats of its outputs (its inputs' come with every message)."""
        for topic, fmt in formats.items():
            assigned = AudioFormat.from_dict(fmt)
            if self.assigned.get(topic) == assigned:
                continue
            self.assigned[topic] = assigned
            declared = self.processor.outputs.get(topic) or self.processor.inputs.get(topic)
            log.info("format assigned topic=%s wire=%s declared=%s%s", topic, assigned, declared,
                     "" if assigned == declared else " (converted here)")
            if topic in self.output_links:
                self.output_links[topic].assigned = assigned  # the switch happens at the next chunk

    def on_subscription(self, topic: str, change: int) -> None:
        stats = self.output_stats.get(topic)
        if stats is None:
            return
        stats.subscribers = max(0, stats.subscribers + change)
        log.info("subscribers topic=%s count=%d", topic, stats.subscribers)
        self.poke()

    def command(self, command: Command) -> None:
        """An order from the orchestrator, to the processor's on_command (on the data thread); a handler's
        exception is logged, as an audio handler's is."""
        try:
            self.processor.on_command(command)
        except Exception:
            if self.node is not None and self.node.strict:
                raise
            log.exception("on_command failed order=%s stream_id=%s", command.order.action, command.stream_id)

    def refuse_subscriber(self, reason: str) -> None:
        count = self.refused_subscribers[reason] = self.refused_subscribers.get(reason, 0) + 1
        if count == 1 or count % 100 == 0:
            log.warning("refused a subscriber's handshake reason=%s count=%d", reason, count)

    def take(self, frames: list[bytes]) -> None:
        """An audio message, as on the wire: handled if its topic is one of the inputs (a handler's
        exception is counted and logged, and the loop goes on)."""
        while not self._formats.empty():
            self.apply_formats(self._formats.get())
        while not self._commands.empty():
            self.command(self._commands.get())
        received = self.receiver.receive(frames)
        if received is None:
            return  # refused (counted and logged), or a topic this processor does not take
        self.handling = True
        try:
            for chunk in received.chunks:
                self._dispatch(chunk)
        except Exception:  # a handler bug must not kill the component: count, log, go on
            if self._node.strict:
                raise
            received.stats.bad += 1
            audio = received.audio
            log.exception("handler failed topic=%s sequence=%d start_ns=%d", received.topic, audio.sequence,
                          audio.start_ns)
        finally:
            self.handling = False

    def _dispatch(self, audio: Audio) -> None:
        processor = self.processor
        processor.on_audio(audio)
        if audio.meta.ssl_directions:
            processor.on_ssl(audio)
        if audio.meta.segmentation_ended:
            processor.on_segment_end(audio)
        if audio.meta.end_of_stream:
            self._on_input_ended(audio)

    def _on_input_ended(self, audio: Audio) -> None:
        ended = self.ended.get(audio.stream_id)
        ended.add(audio.topic)
        if not self.processor.stream_inputs() <= ended:
            return
        self.ended.pop(audio.stream_id)
        self.processor.on_end_of_stream(audio.stream_id, audio)
        notice = {"component_id": self.control.component_id if self.control else "",
                  "component": self.settings.name, "stream_id": audio.stream_id}
        self._send_results(b"end_of_stream", json.dumps(notice).encode(), audio.stream_id)
        log.info("end of stream stream_id=%s", audio.stream_id)

    def _send_results(self, kind: bytes, body: bytes, stream_id: str) -> None:  # signed: esiaf/binding.py
        registration = self.control.registration if self.control else None
        if self._node.send_results(binding.signed(kind, body, registration), stream_id):  # a replay's wait
            self.results_sent += kind == b"result"
        else:
            self.results_dropped += 1
            log.error("result dropped: orchestrator not taking results dropped=%d", self.results_dropped)

    # -- a processor hosted beside the primary ------------------------------------------
    def register_hosted(self, node: Node, transport: Transport) -> None:
        """Registers a processor run beside the primary (with the primary's sockets) and starts its
        heartbeats. Its control thread hands the orchestrator's state to an inproc socket of its own
        ZeroMQ context: the sockets follow the primary's state (its peers); this one is watched
        for "fatal" and formats."""
        self._zmq = zmq.Context()
        self._transport = transport
        state = self._zmq.socket(zmq.PAIR)
        state.setsockopt(zmq.LINGER, 0)
        state.bind(STATE_ADDRESS)
        name = self.processor.service
        self._state_thread = threading.Thread(target=self._watch, args=(state, node), daemon=True,
                                              name=f"esiaf-guest-{name}")
        self._state_thread.start()
        settings = self.settings
        self.control = ControlClient(self._zmq, settings.orchestrator_url, self.registration_request(transport),
                                     self.stats, settings.register_timeout_s, "",
                                     keys.load(orchestrator=False), self.clock_ns)
        registered = self.control.start().local_state()
        self.apply_formats(registered.formats)
        transport.name_consumers(self.control.component_id, registered.consumers)  # its outputs' too
        log.info("hosting guest=%s component_id=%s", name, self.control.component_id)

    def _watch(self, state: zmq.Socket, node: Node) -> None:
        try:
            while True:
                message = parse_to_data_thread(state.recv())  # our own heartbeat thread's: a bug if refused
                if isinstance(message, Fatal):  # the orchestrator will not have it: stop, as it would alone
                    log.error("guest %s stopping the node: %s", self.processor.service, message.error)
                    node.stop(exit_code=1)
                elif isinstance(message, Command):
                    self._commands.put(message)  # carried out on the data thread, at the next message
                else:
                    self._formats.put(message.formats)  # applied on the data thread, at the next message
                    if self._transport is not None:  # who may subscribe to its outputs on the node's socket
                        self._transport.name_consumers(message.component_id, message.consumers)
        except zmq.ContextTerminated:
            pass
        finally:
            state.close()

    def stop_hosted(self) -> None:
        """Unregisters a hosted processor and releases its model."""
        try:
            self.processor.teardown()
        finally:
            if self.control is not None:
                self.control.stop()
            if self._zmq is not None:  # ends the watching thread; on a thread of its own, so that a control
                # thread not yet finished (still registering) cannot hold the node's shutdown
                threading.Thread(target=self._zmq.term, daemon=True, name="esiaf-guest-term").start()
            if self._state_thread is not None:
                self._state_thread.join(timeout=3.0)


def context_of(processor: Processor) -> Context:
    """The processor's context: the one it has (made before it ran), or a new one."""
    if isinstance(processor.context, Context):
        return processor.context
    if processor.context is not None:
        raise TypeError(f"{type(processor).__name__} already has a context of another runtime "
                        f"({type(processor.context).__name__}): a processor runs in one runtime at a time")
    context = Context(processor)
    processor.context = context
    return context


class Node:
    """Runs processors in this process: the first is the primary, the others are hosted beside it."""

    strict = False  # a handler's exception ends the run (in tests), instead of being counted and logged

    def __init__(self, processors: Sequence[Processor]):
        if not processors:
            raise ValueError("a node runs at least one processor")
        self.processors = list(processors)
        self.contexts = [context_of(p) for p in self.processors]
        self.primary = self.contexts[0]
        self.exit_code = 0
        self._stop = threading.Event()
        self._hosted_started = False
        self._zmq: zmq.Context | None = None
        self.transport: Transport | None = None
        for context in self.contexts:
            context.node = self
            if context.stop_asked is not None:
                self.stop(context.stop_asked)

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self, exit_code: int = 0) -> None:
        self.exit_code = self.exit_code or exit_code
        self._stop.set()
        if self.transport is not None:
            self.transport.stop()  # a long wait for input, or a replay's for a consumer, ends now

    @property
    def _wire(self) -> Transport:  # the sockets: made by run() before it registers, closed when it returns
        if self.transport is None:
            raise RuntimeError("the sockets are used before run() made them")
        return self.transport

    @property
    def _handling(self) -> bool:  # inside a handler: audio input waits, so handlers never nest
        return any(context.handling for context in self.contexts)

    # -- running ---------------------------------------------------------------------
    def run(self) -> int:
        """Set up, register, process until stopped; returns the exit code."""
        signals.install(self.stop, lambda: self.transport.reload_keys_soon() if self.transport else None)
        try:
            try:  # before setup(): a bad key file fails at once, not after a model has loaded
                curve = keys.load(orchestrator=False)
            except keys.KeyFileError as exc:
                raise SetupError(str(exc)) from None
            for context in self.contexts[1:]:  # the hosted ones' models load before the primary's
                context.processor.setup()
            self._run_primary(curve)
        finally:
            for context in self.contexts[1:]:
                context.stop_hosted()
        return self.exit_code

    def _run_primary(self, curve: keys.Curve | None) -> None:
        primary = self.primary
        processor = primary.processor
        processor.setup()
        self._check_hosted()
        for context in self.contexts:
            context.declared()
            context.output_links = {t: OutputLink(t, f) for t, f in context.processor.outputs.items()}
        self._zmq = zmq.Context()
        try:
            try:
                self.transport = Transport(self._zmq, inputs=processor.inputs, has_outputs=bool(processor.outputs),
                                           bind_host=primary.settings.bind_host,
                                           audio_port=primary.settings.audio_port,
                                           advertise_host=primary.settings.advertise_host, curve=curve,
                                           audio_queue=primary.settings.audio_queue,
                                           replays=primary.receiver.replays, identity=processor.instance_id)
            except TransportError as exc:
                raise SetupError(str(exc)) from None
            settings = primary.settings
            primary.control = ControlClient(self._zmq, settings.orchestrator_url,
                                            primary.registration_request(self.transport), primary.stats,
                                            settings.register_timeout_s, settings.health_file, curve,
                                            primary.clock_ns)
            self.transport.on_busy = primary.control.busy  # audio or results moving: the heartbeat stays fast
            registration = primary.control.start()
            self._apply_state(registration.local_state())
            if processor.produces():
                processor.produce()
            else:  # a consumer: sleeps until input, a control message or stop() wakes it
                while not self.stopping:
                    self.service(IDLE_WAIT_MS)
        finally:
            self._shutdown()

    def _check_hosted(self) -> None:
        """Each hosted processor hears one of the primary's topics, and one with outputs needs the
        primary's output socket."""
        primary = self.primary.processor
        heard = {*primary.inputs, *primary.outputs}
        for context in self.contexts[1:]:
            hosted = context.processor
            if not set(hosted.inputs) & heard:
                raise SetupError(f"guest {hosted.service} hears {', '.join(hosted.inputs) or 'nothing'}, "
                                 f"and {primary.service} receives or publishes only {', '.join(sorted(heard))}")
            if hosted.outputs and not primary.outputs:
                raise SetupError(f"guest {hosted.service} publishes {', '.join(hosted.outputs)}, and "
                                 f"{primary.service} has no output socket to send it from")

    def service(self, timeout_ms: float) -> None:
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
                (self.publisher_of(event[0]) or self.primary).on_subscription(*event)
            elif kind == "refused":
                self.primary.refuse_subscriber(event)
            else:
                if event:
                    taken[event[0]] = taken.get(event[0], 0) + 1
                self.deliver(event)
        for frame, count in taken.items():
            if (stats := self.primary.input_stats.get(topic_name(frame))) is not None:
                stats.took_back_to_back(count)

    def deliver(self, frames: list[bytes], after: Context | None = None) -> None:
        """An audio message, as on the wire, to every processor (after ``after``, its publisher) that
        takes its topic, in order."""
        contexts = self.contexts if after is None else self.contexts[self.contexts.index(after) + 1:]
        for context in contexts:
            if context is not self.primary and context.control is not None:
                context.control.busy()  # its heartbeat stays fast while it works (the transport wakes the node)
            context.take(frames)

    def send_audio(self, context: Context, topic: str, msg: pb.AugmentedAudio) -> bool:
        """Sends a processor's audio message: whether it went (esiaf/transport.py); the processors
        after it hear it as sent."""
        sent, frames = self._wire.send_audio(topic, msg)  # a replay's waits for the consumers
        self.deliver(frames, after=context)
        if sent and not self._handling:  # a producer; a handler's caller services the sockets when it returns
            self.service(0)
        return sent

    def send_results(self, frames: list[bytes], stream_id: str) -> bool:
        return self._wire.send_results(frames, stream_id)

    def publisher_of(self, topic: str) -> Context | None:
        """The processor whose output ``topic`` is (a hosted one's first), if any."""
        return next((c for c in [*self.contexts[1:], self.primary] if topic in c.output_stats), None)

    def _apply_state(self, state: LocalState | Fatal | Command) -> None:
        if isinstance(state, Command):
            self.primary.command(state)
            return
        if isinstance(state, Fatal):
            log.error("stopping: %s", state.error)
            self.stop(exit_code=1)
            return
        wire = self._wire
        wire.connect_peers({e for endpoints in state.peers.values() for e in endpoints}, state.peer_keys)
        wire.connect_results(state.results_endpoint)
        wire.take_streams(state.streams)
        wire.name_consumers(state.component_id, state.consumers)
        self.primary.apply_formats(state.formats)
        if not self._hosted_started and not self.stopping:  # the first state: registered, sockets made
            self._hosted_started = True
            for context in self.contexts[1:]:
                context.register_hosted(self, wire)

    def _shutdown(self) -> None:
        try:
            self.primary.processor.teardown()
        finally:
            if self.primary.control is not None:
                self.primary.control.stop()
            if self.transport is not None:
                self.transport.close()
            if self._zmq is not None:
                self._zmq.term()

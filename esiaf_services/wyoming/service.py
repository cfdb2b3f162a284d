"""Wyoming service: a Wyoming speech-to-text server whose sessions are streams of the pipeline.

Each client session (``audio-start`` ... ``audio-stop``) becomes a stream of its own
(``wyoming-<random>``), announced to the orchestrator as a grabber announces its file and published on
``wyoming/audio`` (16 kHz, 16-bit, mono: converted from what the client sends), ended with
``end_of_stream``; the transcript is what the orchestrator fuses for that stream (esiaf_services/
wyoming/server.py). The Wyoming server runs on an asyncio loop in a thread of its own; the node's
thread (this module) does what touches the sockets: it takes the sessions' audio from a queue,
stamps it from sample counts and publishes it; and it hears the vad's speech (``vad/speech``), whose
starts and ends a session that asks for them gets as ``voice-started`` / ``voice-stopped``.
"""
from __future__ import annotations

import asyncio
import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

from esiaf import Audio, Component, SampleClock, SetupError
from esiaf_services.wyoming.commands import PUBLISHED, Chunk, Started
from esiaf_services.wyoming.server import Server
from esiaf_services.wyoming.settings import WyomingSettings

log = logging.getLogger(__name__)

# the node's thread waits on its sockets this long at most (a session's command wakes it at once): how soon it
# sees that the server's thread has died
IDLE_WAIT_MS = 1_000


@dataclass
class Listener:
    """A session that asked to hear where the vad finds speech in its stream."""
    on_voice: Callable[[str, int], None]
    origin_ns: int
    speaking: bool = False

    def ms(self, time_ns: int) -> int:
        return max(0, (time_ns - self.origin_ns) // 1_000_000)


class WyomingSource(Component):
    """Serves Wyoming speech-to-text: each client's audio into the pipeline, its transcript back."""

    service = "wyoming"
    kind = "other"
    Settings = WyomingSettings
    settings: WyomingSettings

    options = {"port": "the Wyoming server's TCP port (default 10300)",  # noqa: RUF012 (as the grabber's)
               "listen_host": "where the Wyoming server listens (default 127.0.0.1)"}

    def __init__(self, settings: WyomingSettings):
        super().__init__(settings)
        self.add_output(settings.topic, PUBLISHED)
        if settings.speech_topic:
            self.add_input(settings.speech_topic, PUBLISHED)
        self.listeners: dict[str, Listener] = {}
        self.commands: queue.SimpleQueue[Started | Chunk] = queue.SimpleQueue()
        self.clocks: dict[str, SampleClock] = {}
        self.info.update(sessions=0, served=0, refused={})

    def produce(self) -> None:
        s = self.settings
        if s.wait_for_subscribers and not self.wait_for_subscribers(s.topic, s.wait_for_subscribers,
                                                                     s.wait_timeout_s) and not self.stopping:
            log.warning("topic=%s has fewer than %d subscribers after %g s; serving anyway",
                        s.topic, s.wait_for_subscribers, s.wait_timeout_s)
        server = Server(s, self.submit, self.commands.qsize, self.info)
        thread = threading.Thread(target=asyncio.run, args=(server.serve(),), name="esiaf-wyoming", daemon=True)
        thread.start()
        if not server.listening.wait(10.0) or server.failure:
            raise SetupError(server.failure or f"the Wyoming server did not listen on {s.listen_host}:{s.port}")
        log.info("serving Wyoming host=%s port=%d topic=%s", s.listen_host, s.port, s.topic)
        try:
            node = self.context.node
            assert node is not None  # produce() runs in a node
            while not self.stopping and thread.is_alive():
                node.service(IDLE_WAIT_MS)  # the vad's speech, control messages, subscriptions; or woken
                while True:
                    try:
                        command = self.commands.get_nowait()
                    except queue.Empty:
                        break
                    self.handle(command)
        finally:
            server.stop()
            thread.join(timeout=5.0)

    def submit(self, command: Started | Chunk) -> None:
        """From the server's thread: a command for the node's thread, which is woken for it."""
        self.commands.put(command)
        node = self.context.node
        if node is not None and node.transport is not None:
            node.transport.wake()

    def handle(self, command: Started | Chunk) -> None:
        """On the node's thread: announce a session's stream, or publish its audio."""
        if isinstance(command, Started):
            origin_ns = self.clock_ns()
            self.clocks[command.stream_id] = SampleClock(origin_ns, PUBLISHED.sample_rate_hz)
            if command.on_voice is not None:
                self.listeners[command.stream_id] = Listener(command.on_voice, origin_ns)
            # not realtime: a client may send faster than real time, and its audio then waits for the pipeline
            self.announce_stream(origin_ns, command.stream_id, format=PUBLISHED.to_dict(), realtime=False,
                                 **command.info)
            return
        clock = self.clocks.get(command.stream_id)
        if clock is None:
            return  # a session whose start was never announced: nothing to end
        start_ns, end_ns = clock.advance(len(command.samples))
        self.publish(self.settings.topic, command.samples, start_ns, end_ns, stream_id=command.stream_id,
                     end_of_stream=command.last)
        if command.last:
            del self.clocks[command.stream_id]

    def on_audio(self, audio: Audio) -> None:
        """The vad's speech: its first chunk of an utterance is a voice's start."""
        listener = self.listeners.get(audio.stream_id)
        if listener is not None and not listener.speaking and audio.payload:
            listener.speaking = True
            listener.on_voice("started", listener.ms(audio.start_ns))

    def on_segment_end(self, audio: Audio) -> None:
        listener = self.listeners.get(audio.stream_id)
        if listener is not None and listener.speaking:
            listener.speaking = False
            listener.on_voice("stopped", listener.ms(audio.end_ns))

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """The vad has ended a session's stream: nothing more to tell it (its audio was ended here)."""
        self.listeners.pop(stream_id, None)

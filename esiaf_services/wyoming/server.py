"""The Wyoming side of the wyoming service: one :class:`Session` handler per client connection,
on the ``wyoming`` package's ``AsyncTcpServer``.

A session answers ``describe`` with ``info`` (one ``asr`` program), and turns ``transcribe``,
``audio-start``, ``audio-chunk`` ... ``audio-stop`` into a stream of the pipeline and its fused
text into one ``transcript`` (the utterances' texts in capture order, joined by a space). Whatever
goes wrong is said to the client as an ``error`` event (with a ``code``) before the connection is
closed. Events are read with bounds (:func:`read_event`): the package's reader takes any length a
peer announces and ends a connection that sends garbage without a word.
"""
from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import json
import logging
import threading
import uuid
from collections import Counter
from collections.abc import Callable
from typing import Any
from urllib.parse import urlencode

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import WebSocketException
from wyoming.asr import Transcribe, Transcript, TranscriptChunk, TranscriptStart, TranscriptStop
from wyoming.audio import AudioChunk, AudioStart, AudioStop
from wyoming.error import Error
from wyoming.event import Event
from wyoming.info import AsrModel, AsrProgram, Attribution, Describe, Info
from wyoming.ping import Ping, Pong
from wyoming.server import AsyncEventHandler, AsyncTcpServer
from wyoming.vad import VoiceStarted, VoiceStopped

from esiaf import auth
from esiaf.formats import AudioFormat
from esiaf_services.wyoming.audio import AudioError, ClientAudio, client_format
from esiaf_services.wyoming.commands import PUBLISHED, Chunk, Started
from esiaf_services.wyoming.settings import WyomingSettings

log = logging.getLogger(__name__)

ATTRIBUTION = Attribution(name="ESIAF", url="")  # pyproject.toml names no project URL to give

LOG_EVERY = 100  # a refusal is logged the first time for its reason, then every 100th
# commands waiting for the node's thread (every session's; a chunk is what the client sent in one event): past
# it, a session reads no more from its client until the pipeline has taken some, so TCP slows the client down
MAX_BACKLOG = 500
BACKLOG_WAIT_S = 0.01


def esiaf_version() -> str | None:
    """The installed esiaf distribution's version, as describe gives it (None: not installed, run from a tree)."""
    try:
        return importlib.metadata.version("esiaf")
    except importlib.metadata.PackageNotFoundError:
        return None


class ProtocolError(Exception):
    """What the client sent is not a Wyoming event within the bounds: said with ``code``, then closed."""

    def __init__(self, code: str, text: str):
        super().__init__(text)
        self.code = code


async def read_event(reader: asyncio.StreamReader, max_data_bytes: int, max_payload_bytes: int) -> Event | None:
    """The next event (a JSON header line, optional data, optional payload), or None when the peer has
    gone; a header that is not JSON, or a length over the bounds, is a :class:`ProtocolError`."""
    try:
        line = await reader.readline()
    except ValueError:  # no newline within the reader's limit (64 KiB): not a Wyoming header
        raise ProtocolError("bad-event", "an event header longer than 64 KiB: not a Wyoming event") from None
    if not line.endswith(b"\n"):
        return None
    try:
        header = json.loads(line)
    except ValueError:
        raise ProtocolError("bad-event", "an event header that is not JSON: not a Wyoming event") from None
    if not isinstance(header, dict) or not isinstance(header.get("type"), str) \
            or not isinstance(header.get("data", {}), dict):
        raise ProtocolError("bad-event", "an event header without a type: not a Wyoming event")
    data_length, payload_length = header.get("data_length") or 0, header.get("payload_length") or 0
    for name, length, bound in (("data", data_length, max_data_bytes), ("payload", payload_length, max_payload_bytes)):
        if not isinstance(length, int) or not 0 <= length <= bound:
            raise ProtocolError("too-large", f"{header['type']}: {name}_length {length!r}; at most {bound} bytes")
    data = dict(header.get("data") or {})
    try:
        if data_length:
            more = json.loads(await reader.readexactly(data_length))
            if not isinstance(more, dict):
                raise ProtocolError("bad-event", f"{header['type']}: its data is not a JSON object")
            data.update(more)
        payload = await reader.readexactly(payload_length) if payload_length else None
    except asyncio.IncompleteReadError:
        return None  # gone mid-event
    except ValueError:
        raise ProtocolError("bad-event", f"{header['type']}: its data is not JSON") from None
    return Event(type=header["type"], data=data, payload=payload)


def transcript_text(fused: dict[int, dict[str, Any]]) -> str:
    """The fused utterances' texts in capture order, joined by a space: each its best hypothesis's text (with
    a closed set: the allowed sentence; out of the set: what the recogniser heard)."""
    texts = []
    for message in sorted(fused.values(), key=lambda m: m["anchor"]["span"]["start_ns"]):
        hypotheses = (message["anchor"].get("speech") or {}).get("hypotheses") or []
        if hypotheses:
            best = hypotheses[0]
            text = best.get("raw_text", "") if best.get("out_of_set") else best.get("text") or best.get("raw_text", "")
            if text.strip():
                texts.append(text.strip())
    return " ".join(texts)


class Server:
    """The Wyoming server of one wyoming service: its settings, the sessions' shared counters, and how
    commands reach the node's thread (``submit``)."""

    def __init__(self, settings: WyomingSettings, submit: Callable[[Started | Chunk], None],
                 backlog: Callable[[], int], info: dict[str, Any]):
        self.settings = settings
        self.submit = submit
        self.backlog = backlog  # commands the node's thread has not taken yet
        self.info = info  # reported with the service's heartbeats
        self.refused: Counter[str] = Counter()
        self.sessions = 0
        self.listening = threading.Event()
        self.failure = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: AsyncTcpServer | None = None
        self._stopped: asyncio.Event | None = None
        ws_url = settings.orchestrator_url.replace("http", "ws", 1).rstrip("/")
        self.feed_url = f"{ws_url}/ws/fused"

    async def serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        server = AsyncTcpServer(self.settings.listen_host, self.settings.port)
        try:
            await server.start(lambda reader, writer: Session(reader, writer, self))
        except OSError as exc:
            self.failure = f"cannot listen on {self.settings.listen_host}:{self.settings.port}: {exc.strerror}"
            self.listening.set()
            return
        self._server = server
        self.listening.set()
        await self._stopped.wait()
        await server.stop()

    def stop(self) -> None:
        """From another thread: stop listening and close every session."""
        if self._loop is not None and self._stopped is not None:
            with contextlib.suppress(RuntimeError):  # the loop has ended already
                self._loop.call_soon_threadsafe(self._stopped.set)

    def refuse(self, reason: str, peer: str, text: str) -> None:
        """Counts a refusal by reason and logs the first of each reason and every LOG_EVERY-th."""
        self.refused[reason] += 1
        self.info["refused"] = dict(self.refused)
        if self.refused[reason] % LOG_EVERY == 1:
            log.warning("wyoming refused reason=%s peer=%s count=%d: %s", reason, peer, self.refused[reason], text)

    def describe(self) -> Info:
        s = self.settings
        model = AsrModel(name=s.model, description=s.model_description or s.model, attribution=ATTRIBUTION,
                         installed=True, version=None, languages=list(s.languages))
        return Info(asr=[AsrProgram(name="esiaf", description="ESIAF speech-analysis pipeline",
                                    attribution=ATTRIBUTION, installed=True, version=esiaf_version(), models=[model],
                                    supports_transcript_streaming=s.stream_transcripts)])


class Session(AsyncEventHandler):
    """One client connection: its requests, and at most one stream at a time."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, server: Server):
        super().__init__(reader, writer)
        self.server = server
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.language: str | None = None
        self.voice_events = False  # asked for in transcribe's context: {"voice_events": true}
        self.stream_id: str | None = None
        self.audio: ClientAudio | None = None
        self.published_s = 0.0
        self.feed: ClientConnection | None = None
        self.fused: asyncio.Task[str] | None = None
        self.voice_writes: set[asyncio.Task[None]] = set()  # voice events being written (kept from the collector)
        self.streamed = ""  # the transcript so far sent in transcript-chunk events (None sent: "")
        self.stream_started = False  # transcript-start sent for the open stream

    async def run(self) -> None:
        """Events until the client goes, is refused or idles; every refusal an ``error`` event first."""
        s = self.server.settings
        if self.server.sessions >= s.max_sessions:
            await self.refuse("busy", f"{s.max_sessions} sessions are served already; try again later")
            self.writer.close()
            return
        self.server.sessions += 1
        self.server.info["sessions"] = self.server.sessions
        try:
            while True:
                idle_s = s.idle_timeout_s if self.stream_id else s.connection_idle_s
                try:
                    event = await asyncio.wait_for(read_event(self.reader, s.max_data_bytes, s.max_chunk_bytes),
                                                   idle_s)
                except TimeoutError:
                    await self.refuse("idle", f"nothing came for {idle_s:g} s"
                                      + ("; the stream is ended without a transcript" if self.stream_id else ""))
                    break
                if event is None or not await self.handle_event(event):
                    break
        except ProtocolError as exc:
            await self.refuse(exc.code, str(exc))
        except (ConnectionError, OSError) as exc:
            log.info("wyoming session peer=%s lost: %s", self.peer, exc)
        finally:
            await self.end_stream()
            self.server.sessions -= 1
            self.server.info["sessions"] = self.server.sessions
            self.writer.close()

    async def stop(self) -> None:
        """The server is stopping (the service was told to): the client is told so before it is closed."""
        await self.refuse("stopping", "the server is stopping; the stream is ended without a transcript"
                          if self.stream_id else "the server is stopping")
        await super().stop()

    async def refuse(self, code: str, text: str) -> None:
        self.server.refuse(code, self.peer, text)
        with contextlib.suppress(ConnectionError, OSError):
            await self.write_event(Error(text=text, code=code).event())

    async def handle_event(self, event: Event) -> bool:
        if Describe.is_type(event.type):
            await self.write_event(self.server.describe().event())
        elif Ping.is_type(event.type):
            await self.write_event(Pong(text=Ping.from_event(event).text).event())
        elif Transcribe.is_type(event.type):
            transcribe = Transcribe.from_event(event)
            self.language = transcribe.language
            self.voice_events = isinstance(transcribe.context, dict) and transcribe.context.get("voice_events") is True
        elif AudioStart.is_type(event.type):
            if self.stream_id:
                raise ProtocolError("bad-order", "audio-start while a stream is open: send audio-stop first")
            await self.start(event.data)
        elif AudioChunk.is_type(event.type):
            await self.chunk(event)
        elif AudioStop.is_type(event.type):
            return await self.audio_stopped()
        else:
            log.debug("wyoming session peer=%s ignored event=%s", self.peer, event.type)
        return True

    async def start(self, data: dict[str, Any]) -> None:
        """Opens the session's stream: the fused results' feed first (nothing missed), then the announcement."""
        fmt = self.format_of(data)
        stream_id = f"wyoming-{uuid.uuid4().hex[:12]}"
        streaming = self.server.settings.stream_transcripts
        url = f"{self.server.feed_url}?{urlencode({'stream': stream_id} | ({'partials': 1} if streaming else {}))}"
        try:
            self.feed = await connect(url, additional_headers=auth.headers(), open_timeout=10.0,
                                      ssl=auth.tls_context() if url.startswith("wss:") else None)
        except (OSError, TimeoutError, WebSocketException) as exc:
            raise ProtocolError("unavailable", f"the pipeline's orchestrator does not answer: {exc}") from None
        self.fused = asyncio.create_task(self.collect(self.feed), name=f"fused {stream_id}")
        self.stream_id, self.audio, self.published_s = stream_id, ClientAudio(fmt, PUBLISHED), 0.0
        info = {"source": "wyoming", "client": self.peer, "client_format": fmt.to_dict()}
        self.streamed, self.stream_started = "", False
        if streaming:  # the stream of transcript chunks starts with the audio (the protocol's order)
            await self.write_event(TranscriptStart(language=self.language).event())
            self.stream_started = True
        self.server.submit(Started(stream_id, info, self.voice_listener() if self.voice_events else None))
        log.info("wyoming session peer=%s stream_id=%s format=%s", self.peer, stream_id, fmt)

    def voice_listener(self) -> Callable[[str, int], None]:
        """What the node's thread calls as the vad hears a voice start or stop: the event, written from the loop."""
        loop = asyncio.get_running_loop()

        async def send(kind: str, ms: int) -> None:
            event = VoiceStarted(timestamp=ms) if kind == "started" else VoiceStopped(timestamp=ms)
            with contextlib.suppress(ConnectionError, OSError):
                await self.write_event(event.event())

        def write(kind: str, ms: int) -> None:  # on the loop
            task = loop.create_task(send(kind, ms))
            self.voice_writes.add(task)
            task.add_done_callback(self.voice_writes.discard)

        def heard(kind: str, ms: int) -> None:  # on the node's thread
            with contextlib.suppress(RuntimeError):  # the loop has ended: the session is gone
                loop.call_soon_threadsafe(write, kind, ms)
        return heard

    def format_of(self, data: dict[str, Any]) -> AudioFormat:
        try:
            return client_format(data.get("rate"), data.get("width"), data.get("channels"))
        except AudioError as exc:
            raise ProtocolError("bad-audio", str(exc)) from None

    async def chunk(self, event: Event) -> None:
        if not self.stream_id:  # audio without audio-start: its own format starts the stream
            await self.start(event.data)
        assert self.audio is not None and self.stream_id is not None
        fmt = self.format_of(event.data)
        if fmt != self.audio.source:  # the client changed format: what soxr holds goes out first
            self.publish(self.audio.convert(b"", last=True))
            self.audio = ClientAudio(fmt, PUBLISHED)
        try:
            samples = self.audio.convert(event.payload or b"")
        except AudioError as exc:
            raise ProtocolError("bad-audio", str(exc)) from None
        self.published_s += len(event.payload or b"") / fmt.bytes_per_frame / fmt.sample_rate_hz
        if self.published_s > self.server.settings.max_session_s:
            raise ProtocolError("too-long", f"more than {self.server.settings.max_session_s:g} s of audio in one "
                                "audio-start ... audio-stop; the stream is ended without a transcript")
        while self.server.backlog() > MAX_BACKLOG:  # the pipeline is behind: let it catch up
            await asyncio.sleep(BACKLOG_WAIT_S)
        self.publish(samples)

    def publish(self, samples: Any, last: bool = False) -> None:
        assert self.stream_id is not None
        self.server.submit(Chunk(self.stream_id, samples, last))

    async def audio_stopped(self) -> bool:
        """audio-stop: the stream ends; its transcript once the orchestrator says the stream has ended."""
        if not self.stream_id or self.audio is None or self.fused is None:
            raise ProtocolError("bad-order", "audio-stop without audio-start")
        self.publish(self.audio.convert(b"", last=True), last=True)
        stream_id, fused = self.stream_id, self.fused
        self.stream_id = None  # ended: a disconnect from now on has nothing to end
        timeout_s = self.server.settings.transcript_timeout_s
        try:
            text = await asyncio.wait_for(fused, timeout_s)
        except (TimeoutError, WebSocketException, OSError) as exc:
            why = f"no end of the stream within {timeout_s:g} s" if isinstance(exc, TimeoutError) else str(exc)
            await self.refuse("no-transcript", f"stream {stream_id}: {why}")
            return False
        finally:
            await self.close_feed()
        self.server.info["served"] = self.server.info.get("served", 0) + 1
        log.info("wyoming transcript peer=%s stream_id=%s text=%r", self.peer, stream_id, text)
        await self.write_event(Transcript(text=text, language=self.language).event())
        if self.stream_started:  # after the transcript, as the protocol asks (it is there for older clients)
            self.stream_started = False
            await self.write_event(TranscriptStop().event())
        return True

    async def collect(self, feed: ClientConnection) -> str:
        """The stream's fused results until its end: the text of their latest revisions. Meanwhile, with
        transcript streaming, what is known for sure so far as transcript-chunk events (:meth:`stream_more`)."""
        fused: dict[int, dict[str, Any]] = {}
        async for text in feed:
            message = json.loads(text)
            if message.get("type") == "stream_end":
                return transcript_text(fused)
            if message.get("type") == "fused_result" and "speech" in message.get("anchor", {}):
                fused[message["id"]] = message
                await self.stream_more(transcript_text(fused))
            elif message.get("type") == "partial" and not message.get("closed"):
                stable = str(message.get("stable") or "").strip()
                await self.stream_more(" ".join(part for part in (transcript_text(fused), stable) if part))
        raise OSError("the orchestrator closed the fused results' websocket")

    async def stream_more(self, known: str) -> None:
        """A transcript-chunk with what ``known`` (the utterances fused so far and the stable words of the one
        going on) adds to what was streamed; nothing if it does not extend it (a chunk is never taken back:
        the final transcript says what was decided)."""
        if not self.stream_started or not known.startswith(self.streamed) or len(known) <= len(self.streamed):
            return
        chunk, self.streamed = known[len(self.streamed):], known
        with contextlib.suppress(ConnectionError, OSError):
            await self.write_event(TranscriptChunk(text=chunk).event())

    async def end_stream(self) -> None:
        """The client went or was refused with a stream open: it ends without a transcript."""
        if self.stream_id is not None:
            if self.audio is not None:
                self.publish(self.audio.convert(b"", last=True), last=True)
            log.info("wyoming session peer=%s stream_id=%s ended without audio-stop", self.peer, self.stream_id)
            self.stream_id = None
        await self.close_feed()

    async def close_feed(self) -> None:
        if self.fused is not None and not self.fused.done():
            self.fused.cancel()
        if self.feed is not None:
            with contextlib.suppress(WebSocketException, OSError):
                await self.feed.close()
        self.feed = self.fused = None

"""esiaf wyoming end to end: the pipeline as processes behind a Wyoming server, its clients the
``wyoming`` package's own AsyncTcpClient, wyoming-bench's (a benchmark from PyPI), and raw sockets
for what no well-behaved client sends."""
from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import wave
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
import soxr
from wyoming.asr import Transcribe, Transcript
from wyoming.audio import AudioChunk, AudioStart, AudioStop
from wyoming.client import AsyncTcpClient
from wyoming.error import Error
from wyoming.event import Event, async_read_event
from wyoming.info import Describe, Info

from esiaf.tools.cli_wyoming import listening
from esiaf.tools.testing import REPO, Launcher, free_port, normalise, poll

pytestmark = pytest.mark.e2e

QUESTIONS = REPO / "examples" / "robocup_questions.wav"
TRUTH = json.loads((REPO / "examples" / "robocup_questions.json").read_text())["sentences"]
START_TIMEOUT_S = 180.0  # the pipeline's start, on a busy machine
IDLE_TIMEOUT_S = 2.0  # the server's idle time for these tests (ESIAF_WYOMING_IDLE_TIMEOUT_S)
MAX_SESSIONS = 4
PIPELINE = ["--grammar", "robocup", "--without", "emotion,gender,voiceid"]


@dataclass
class Server:
    port: int
    process: subprocess.Popen
    log: Path
    url: str  # the orchestrator's
    workdir: Path

    def components(self) -> list[dict]:
        token = (self.workdir / "token").read_text().strip()
        response = httpx.get(f"{self.url}/components", headers={"Authorization": f"Bearer {token}"}, timeout=5)
        response.raise_for_status()
        return response.json()["items"]


@contextlib.contextmanager
def esiaf_wyoming(workdir: Path, pipeline: list[str]) -> Iterator[Server]:
    """``esiaf wyoming`` as a process on free ports, with this module's bounds; stopped (SIGTERM) at the end."""
    port, http_port = free_port(), free_port()
    log = workdir / "esiaf.log"
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_WYOMING_IDLE_TIMEOUT_S": str(IDLE_TIMEOUT_S),
           "ESIAF_WYOMING_MAX_SESSIONS": str(MAX_SESSIONS), "ESIAF_WYOMING_MAX_CHUNK_BYTES": str(256 << 10)}
    with log.open("wb") as out:
        process = subprocess.Popen([sys.executable, "-m", "esiaf", "wyoming", "--port", str(port), "--http-port",
                                    str(http_port), "--workdir", str(workdir / "run"), *pipeline],
                                   cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        poll(lambda: process.poll() is not None or listening("127.0.0.1", port), START_TIMEOUT_S)
        assert process.poll() is None, log.read_text()
        yield Server(port, process, log, f"http://127.0.0.1:{http_port}", workdir / "run")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    with esiaf_wyoming(tmp_path_factory.mktemp("wyoming"), PIPELINE) as started:
        yield started


def read_wav(path: Path) -> tuple[np.ndarray, int]:
    with wave.open(str(path)) as wav:
        assert wav.getsampwidth() == 2 and wav.getnchannels() == 1
        return np.frombuffer(wav.readframes(wav.getnframes()), dtype="<i2"), wav.getframerate()


def truth_text(first: int = 0, last: int | None = None) -> str:
    return normalise(" ".join(s["text"] for s in TRUTH[first:last]))


async def transcribe(port: int, pcm: bytes, rate: int, width: int, channels: int, chunk_s: float = 0.1,
                     stop: bool = True) -> Event:
    """One transcription as Home Assistant asks for it; the first transcript or error event."""
    async with AsyncTcpClient("127.0.0.1", port) as client:
        await client.write_event(Transcribe(language="en").event())
        await client.write_event(AudioStart(rate, width, channels).event())
        step = int(rate * chunk_s) * width * channels
        for offset in range(0, len(pcm), step):
            await client.write_event(AudioChunk(rate, width, channels, pcm[offset:offset + step]).event())
        if stop:
            await client.write_event(AudioStop().event())
        while True:
            event = await asyncio.wait_for(client.read_event(), 120.0)
            assert event is not None, "the server closed the connection without a transcript or an error"
            if Transcript.is_type(event.type) or Error.is_type(event.type):
                return event


async def raw_exchange(port: int, data: bytes) -> Event | None:
    """Sends bytes as they are; the first event the server answers (None: closed without one)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(data)
        await writer.drain()
        while True:  # past the transcript stream's start, which a stream's first audio sends
            event = await asyncio.wait_for(async_read_event(reader), 30.0)
            if event is None or event.type != "transcript-start":
                return event
    finally:
        writer.close()


def describes(port: int) -> bool:
    async def ask() -> Event | None:
        async with AsyncTcpClient("127.0.0.1", port) as client:
            await client.write_event(Describe().event())
            return await asyncio.wait_for(client.read_event(), 10.0)
    event = asyncio.run(ask())
    return event is not None and Info.is_type(event.type)


def text_of(event: Event) -> str:
    assert Transcript.is_type(event.type), event
    return normalise(Transcript.from_event(event).text)


def test_describe_lists_the_recogniser(server):
    async def ask() -> Info:
        async with AsyncTcpClient("127.0.0.1", server.port) as client:
            await client.write_event(Describe().event())
            event = await asyncio.wait_for(client.read_event(), 10.0)
            assert event is not None and Info.is_type(event.type), event
            return Info.from_event(event)
    info = asyncio.run(ask())
    (program,) = info.asr
    assert program.supports_transcript_streaming is True  # from the recogniser's partial results
    assert [model.name for model in program.models] == ["pocketsphinx"]
    assert program.models[0].languages == ["en"]
    assert "RoboCup" in (program.models[0].description or "")


def test_the_demo_transcribed_as_esiaf_run_hears_it(server, tmp_path):
    samples, rate = read_wav(QUESTIONS)
    heard = text_of(asyncio.run(transcribe(server.port, samples.tobytes(), rate, 2, 1)))
    assert heard == truth_text()
    run = Launcher(["--input", str(QUESTIONS), "--fast", "--json", *PIPELINE], tmp_path / "run")
    try:
        assert run.process.wait(timeout=START_TIMEOUT_S) == 0, run.describe()
    finally:
        run.stop()
    fused = sorted((line for line in run.lines if line.get("type") == "fused_result"),
                   key=lambda line: line["anchor"]["span"]["start_ns"])
    assert heard == normalise(" ".join(f["anchor"]["speech"]["hypotheses"][0]["text"] for f in fused))


def test_48khz_stereo_float_is_converted(server):
    samples, rate = read_wav(QUESTIONS)
    first_two = samples[: int(TRUTH[2]["start_s"] * rate) - rate // 2]  # the first two questions
    resampled = soxr.resample(first_two.astype(np.float32) / 32768, rate, 48_000)
    stereo = np.stack([resampled, 0.5 * resampled], axis=1)  # the talker louder on the left
    pcm = (np.clip(stereo, -1, 1 - 2**-31) * 2**31).astype("<i4").tobytes()
    assert text_of(asyncio.run(transcribe(server.port, pcm, 48_000, 4, 2))) == truth_text(0, 2)


def test_two_clients_at_once_get_their_own_text(server):
    samples, rate = read_wav(QUESTIONS)
    cut = int(TRUTH[2]["start_s"] * rate) - rate // 2

    async def both() -> list[Event]:
        return await asyncio.gather(transcribe(server.port, samples[:cut].tobytes(), rate, 2, 1),
                                    transcribe(server.port, samples[cut:].tobytes(), rate, 2, 1))
    first, second = asyncio.run(both())
    assert text_of(first) == truth_text(0, 2)
    assert text_of(second) == truth_text(2)


@pytest.mark.parametrize(("data", "code"), [
    (b"\x00\xff garbage, not JSON\n", "bad-event"),
    (b"x" * (128 << 10), "bad-event"),  # no newline: a header past the reader's limit
    (b'{"type": "audio-chunk", "payload_length": 999999999}\n', "too-large"),
    (b'{"type": "audio-start", "data": {"rate": 16000, "width": 7, "channels": 1}}\n', "bad-audio"),
    (b'{"type": "audio-chunk", "data": {"rate": 16000, "width": 2, "channels": 1}, "payload_length": 3}\nabc',
     "bad-audio"),  # a chunk that stops mid-sample
    (b'{"type": "audio-stop"}\n', "bad-order"),
])
def test_bad_input_gets_an_error_event_and_others_are_served(server, data, code):
    event = asyncio.run(raw_exchange(server.port, data))
    assert event is not None and Error.is_type(event.type), event
    assert Error.from_event(event).code == code
    assert describes(server.port)


def test_a_client_gone_mid_chunk_leaves_the_server_serving(server):
    samples, rate = read_wav(QUESTIONS)
    chunk = samples[:rate].tobytes()
    header = {"type": "audio-chunk", "data": {"rate": rate, "width": 2, "channels": 1},
              "payload_length": len(chunk)}
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(json.dumps(header).encode() + b"\n" + chunk[: len(chunk) // 2])
    first_two = samples[: int(TRUTH[2]["start_s"] * rate) - rate // 2]
    assert text_of(asyncio.run(transcribe(server.port, first_two.tobytes(), rate, 2, 1))) == truth_text(0, 2)


def test_a_client_that_never_stops_gets_an_idle_error(server):
    samples, rate = read_wav(QUESTIONS)
    event = asyncio.run(transcribe(server.port, samples[: 2 * rate].tobytes(), rate, 2, 1, stop=False))
    assert Error.is_type(event.type), event
    assert Error.from_event(event).code == "idle"


def test_sessions_beyond_the_bound_are_refused_with_an_error(server):
    async def crowd() -> Event | None:
        held = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(MAX_SESSIONS)]
        try:
            return await raw_exchange(server.port, b"")
        finally:
            for _, writer in held:
                writer.close()
    event = asyncio.run(crowd())
    assert event is not None and Error.from_event(event).code == "busy"
    poll(lambda: describes(server.port), 10.0)


def test_voice_events_where_the_vad_hears_speech_when_asked(server):
    samples, rate = read_wav(QUESTIONS)
    first_two = samples[: int(TRUTH[2]["start_s"] * rate) - rate // 2].tobytes()

    async def ask() -> list[Event]:
        async with AsyncTcpClient("127.0.0.1", server.port) as client:
            await client.write_event(Transcribe(language="en", context={"voice_events": True}).event())
            await client.write_event(AudioStart(rate, 2, 1).event())
            for offset in range(0, len(first_two), rate // 5):
                await client.write_event(AudioChunk(rate, 2, 1, first_two[offset:offset + rate // 5]).event())
            await client.write_event(AudioStop().event())
            events = []
            while not events or not Transcript.is_type(events[-1].type):
                event = await asyncio.wait_for(client.read_event(), 60.0)
                assert event is not None and not Error.is_type(event.type), event
                events.append(event)
            return events
    events = [e for e in asyncio.run(ask()) if not e.type.startswith("transcript-")]  # streamed: the next test's
    assert [e.type for e in events] == ["voice-started", "voice-stopped"] * 2 + ["transcript"]
    heard = [e.data["timestamp"] / 1000 for e in events[:4]]
    spoken = [t for s in TRUTH[:2] for t in (s["start_s"], s["end_s"])]
    assert all(abs(h - s) < 0.5 for h, s in zip(heard, spoken, strict=True)), (heard, spoken)
    assert text_of(events[-1]) == truth_text(0, 2)


def test_the_transcript_streams_in_chunks_that_are_never_taken_back(server):
    """transcript-start with the audio, transcript-chunk events as the recogniser's stable words and fused
    utterances come, then the transcript and transcript-stop (the order of the protocol's README)."""
    samples, rate = read_wav(QUESTIONS)
    first_three = samples[: int(TRUTH[3]["start_s"] * rate) - rate // 2].tobytes()

    async def ask() -> tuple[Info, list[Event]]:
        async with AsyncTcpClient("127.0.0.1", server.port) as client:
            await client.write_event(Describe().event())
            info = Info.from_event(await asyncio.wait_for(client.read_event(), 10.0))
            await client.write_event(Transcribe(language="en").event())
            await client.write_event(AudioStart(rate, 2, 1).event())
            for offset in range(0, len(first_three), rate // 5):
                await client.write_event(AudioChunk(rate, 2, 1, first_three[offset:offset + rate // 5]).event())
            await client.write_event(AudioStop().event())
            events: list[Event] = []
            while not events or events[-1].type != "transcript-stop":
                event = await asyncio.wait_for(client.read_event(), 60.0)
                assert event is not None and not Error.is_type(event.type), event
                events.append(event)
            return info, events
    info, events = asyncio.run(ask())
    assert info.asr[0].supports_transcript_streaming
    types = [e.type for e in events]
    assert types[0] == "transcript-start" and types[-2:] == ["transcript", "transcript-stop"], types
    assert set(types[1:-2]) == {"transcript-chunk"} and len(types) - 3 >= 3, types  # several chunks
    streamed = "".join(e.data["text"] for e in events if e.type == "transcript-chunk")
    assert normalise(streamed) == text_of(events[-2]) == truth_text(0, 3)


def test_wyoming_bench_from_pypi_transcribes_every_question(server, tmp_path):
    """wyoming-bench, a client no one here wrote: its corpus is the demo's questions, one WAV each."""
    bench = shutil.which("wyoming-bench") or str(Path(sys.executable).parent / "wyoming-bench")
    if not Path(bench).is_file():
        pytest.skip("wyoming-bench is not installed (the test extra of pyproject.toml has it)")
    samples, rate = read_wav(QUESTIONS)
    for n, sentence in enumerate(TRUTH):
        first, last = int((sentence["start_s"] - 0.5) * rate), int((sentence["end_s"] + 0.5) * rate)
        with wave.open(str(tmp_path / f"q{n}.wav"), "wb") as out:
            out.setnchannels(1)
            out.setsampwidth(2)
            out.setframerate(rate)
            out.writeframes(samples[max(0, first):last].tobytes())
        (tmp_path / f"q{n}.txt").write_text(sentence["text"])
    done = subprocess.run([bench, "stt", "--corpus", str(tmp_path), "--mode", "non_streaming", "--rounds", "1",
                           "--warmup", "0", f"127.0.0.1:{server.port}"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"ok={len(TRUTH)} fail=0" in done.stdout, done.stdout
    assert "WER=0.0%" in done.stdout, done.stdout


def test_a_server_told_to_stop_tells_its_clients(tmp_path):
    """SIGTERM to esiaf wyoming: a client in the middle of a stream gets an error event, not a bare close."""
    with esiaf_wyoming(tmp_path, ["--without", "emotion,gender,voiceid"]) as own:
        async def stopped_mid_stream() -> Event | None:
            async with AsyncTcpClient("127.0.0.1", own.port) as client:
                await client.write_event(AudioStart(16000, 2, 1).event())
                await client.write_event(AudioChunk(16000, 2, 1, bytes(3200)).event())
                await client.write_event(Describe().event())  # answered: the chunk has been taken
                assert (await asyncio.wait_for(client.read_event(), 10.0)).type == "transcript-start"
                assert Info.is_type((await asyncio.wait_for(client.read_event(), 10.0)).type)
                os.killpg(own.process.pid, signal.SIGTERM)
                return await asyncio.wait_for(client.read_event(), 30.0)
        event = asyncio.run(stopped_mid_stream())
        assert event is not None and Error.is_type(event.type), event
        assert Error.from_event(event).code == "stopping"
        assert own.process.wait(timeout=30) == 0


def test_refusals_are_counted_by_code_in_the_services_heartbeat(server):
    def refused() -> dict[str, int]:
        wyoming = next(c for c in server.components() if c["name"] == "wyoming" and c["status"] == "alive")
        return wyoming["stats"]["info"].get("refused") or {}
    before = refused().get("bad-order", 0)
    event = asyncio.run(raw_exchange(server.port, b'{"type": "audio-stop"}\n'))
    assert event is not None and Error.from_event(event).code == "bad-order"
    poll(lambda: refused().get("bad-order", 0) == before + 1, 30.0)

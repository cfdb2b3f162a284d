"""esiaf wyoming: transcript latency after ``audio-stop``, alone and with N clients at once.

It starts ``esiaf wyoming`` (the real pipeline as processes) and talks to it with the ``wyoming``
package's own AsyncTcpClient, as Home Assistant does: ``transcribe``, ``audio-start``, 100 ms
``audio-chunk`` events paced in real time, ``audio-stop``, then it waits for the ``transcript``.
Each command is 3 s of examples/robocup_questions.wav around one of its five questions (16 kHz,
16-bit mono; centred, or cut --tail-s after the last word); latency = the transcript's arrival - the
moment audio-stop was sent. A transcript is right when it is the question's text (lower case, no
punctuation); a wrong one is shown on stderr.

    python bench/wyoming.py [--asr pocketsphinx|whisper] [--grammar robocup|FILE|''] [--rounds 10]
                            [--clients 1,5,10,20] [--without emotion,gender,voiceid]

It prints ``name=value`` lines: ``latency_ms_p50`` / ``_p95`` / ``_max`` of the single client (commands
centred on their question; ``tight_...``: cut --tail-s after the last word), and
for each N of --clients ``clients_N_latency_ms_p50`` / ``_p95`` / ``_max``, ``clients_N_right`` and
``clients_N_errors``.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import wave
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]
sys.path.insert(0, str(REPO))

from wyoming.asr import Transcribe, Transcript  # noqa: E402
from wyoming.audio import AudioChunk, AudioStart, AudioStop  # noqa: E402
from wyoming.client import AsyncTcpClient  # noqa: E402
from wyoming.error import Error  # noqa: E402

from esiaf.tools.cli_wyoming import listening  # noqa: E402
from esiaf.tools.testing import free_port, normalise  # noqa: E402

QUESTIONS = REPO / "examples" / "robocup_questions.wav"
COMMAND_S = 3.0
CHUNK_S = 0.1
START_TIMEOUT_S = 300.0


def commands(tail_s: float | None) -> list[tuple[bytes, str]]:
    """The five 3 s commands, each with its question's text: centred on the question (``tail_s`` None:
    about 0.7 s of silence after it, in which the vad ends the utterance before audio-stop), or ending
    ``tail_s`` after its last word (the utterance is ended by the stream's end, after audio-stop)."""
    with wave.open(str(QUESTIONS)) as wav:
        rate = wav.getframerate()
        pcm = wav.readframes(wav.getnframes())
    sentences = json.loads(QUESTIONS.with_suffix(".json").read_text())["sentences"]
    out = []
    for sentence in sentences:
        end_s = (sentence["start_s"] + sentence["end_s"] + COMMAND_S) / 2 if tail_s is None \
            else sentence["end_s"] + tail_s
        first = max(0, int((end_s - COMMAND_S) * rate))  # the first question starts 1.2 s in: its is shorter
        out.append((pcm[2 * first: 2 * int(end_s * rate)], normalise(sentence["text"])))
    return out


async def transcribe(port: int, pcm: bytes, rate: int = 16_000) -> tuple[float, str | None]:
    """One command in real time; (ms from audio-stop to the transcript, its text or None on an error)."""
    async with AsyncTcpClient("127.0.0.1", port) as client:
        await client.write_event(Transcribe(language="en").event())
        await client.write_event(AudioStart(rate, 2, 1).event())
        step = int(rate * CHUNK_S) * 2
        started = time.monotonic()
        for n, offset in enumerate(range(0, len(pcm), step), start=1):
            await client.write_event(AudioChunk(rate, 2, 1, pcm[offset:offset + step]).event())
            await asyncio.sleep(max(0.0, started + n * CHUNK_S - time.monotonic()))
        stopped = time.monotonic()
        await client.write_event(AudioStop().event())
        while True:
            event = await client.read_event()
            if event is None or Error.is_type(event.type):
                return (time.monotonic() - stopped) * 1000, None
            if Transcript.is_type(event.type):
                return (time.monotonic() - stopped) * 1000, normalise(Transcript.from_event(event).text)


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))] if ordered else float("nan")


def report(prefix: str, outcomes: list[tuple[float, str | None]], truths: list[str]) -> None:
    latencies = [ms for ms, text in outcomes if text is not None]
    print(f"{prefix}latency_ms_p50={percentile(latencies, 0.5):.0f}")
    print(f"{prefix}latency_ms_p95={percentile(latencies, 0.95):.0f}")
    print(f"{prefix}latency_ms_max={max(latencies, default=float('nan')):.0f}")
    for (_, text), truth in zip(outcomes, truths, strict=True):
        if text != truth:
            print(f"{prefix}wrong: {text!r} for {truth!r}", file=sys.stderr)
    print(f"{prefix}right={sum(text == truth for (_, text), truth in zip(outcomes, truths, strict=True))}"
          f"/{len(outcomes)}")
    print(f"{prefix}errors={sum(text is None for _, text in outcomes)}")


async def measure(port: int, rounds: int, crowds: list[int], tail_s: float) -> None:
    for prefix, tail in (("", None), ("tight_", tail_s)):
        chosen = [commands(tail)[n % 5] for n in range(rounds)]
        report(prefix, [await transcribe(port, pcm) for pcm, _ in chosen], [truth for _, truth in chosen])
    cmds = commands(None)
    for count in crowds:
        chosen = [cmds[n % len(cmds)] for n in range(count)]
        outcomes = await asyncio.gather(*(transcribe(port, pcm) for pcm, _ in chosen))
        report(f"clients_{count}_", list(outcomes), [truth for _, truth in chosen])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--asr", default="pocketsphinx", choices=("pocketsphinx", "whisper"))
    parser.add_argument("--grammar", default="robocup")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--clients", default="1,5,10,20")
    parser.add_argument("--without", default="emotion,gender,voiceid")
    parser.add_argument("--tail-s", type=float, default=0.2, help="tight commands: audio after the last word")
    args = parser.parse_args()
    crowds = [int(n) for n in args.clients.split(",") if n]
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="esiaf-bench-wyoming-") as tmp:
        command = [sys.executable, "-m", "esiaf", "wyoming", "--port", str(port), "--http-port", str(free_port()),
                   "--workdir", tmp, "--asr", args.asr, *(["--grammar", args.grammar] if args.grammar else []),
                   *(["--without", args.without] if args.without else [])]
        process = subprocess.Popen(command, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                                   start_new_session=True)
        try:
            deadline = time.monotonic() + START_TIMEOUT_S
            while not listening("127.0.0.1", port):
                if process.poll() is not None or time.monotonic() > deadline:
                    print(f"esiaf wyoming did not start (exit {process.poll()})", file=sys.stderr)
                    return 1
                time.sleep(0.2)
            print(f"asr={args.asr} grammar={args.grammar or '-'} command_s={COMMAND_S} chunk_s={CHUNK_S}")
            asyncio.run(measure(port, args.rounds, crowds, args.tail_s))
        finally:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait(timeout=30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

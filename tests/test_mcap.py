"""Sessions recorded to MCAP and replayed, through the real pipeline (every service a process): the
recording is read with the ``mcap`` package's own reader and decoded by ``mcap-protobuf-support``'s
decoder from the schemas embedded in it, never by the code under test."""
from __future__ import annotations

import itertools
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import soundfile
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.writer import Writer

from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.testing import REPO, Launcher, free_port, poll

pytestmark = pytest.mark.e2e
DEMO = REPO / "examples" / "robocup_questions.wav"
QUESTIONS = 5  # the demo's questions: one fused result each


def esiaf(*args: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s)


def run(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    done = esiaf("run", "--grammar", "robocup", "--fast", "--port", str(free_port()), "--workdir", str(workdir), *args)
    assert done.returncode == 0, done.stderr
    return done


def read(path: Path) -> dict[str, list]:
    """Every message of a recording, decoded from its embedded schemas, by topic (log time order)."""
    messages: dict[str, list] = {}
    with path.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        assert reader.get_summary() is not None  # finished: index and footer written
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            assert schema is not None and schema.encoding == "protobuf"
            messages.setdefault(channel.topic, []).append(decoded)
    return messages


def utterances(messages: dict[str, list]) -> list[tuple]:
    """Each fused result's latest revision as (text, voice, azimuth rounded to 10 degrees), by window start."""
    latest = {}
    for fused in messages["fused"]:
        if fused.id not in latest or fused.revision >= latest[fused.id].revision:
            latest[fused.id] = fused
    return [(fused.anchor.speech.hypotheses[0].text, fused.aggregates.voice_id.label,
             round(fused.aggregates.ssl.azimuth_deg, -1) if fused.aggregates.ssl.directions else None)
            for fused in sorted(latest.values(), key=lambda fused: fused.anchor.span.start_ns)]


def test_a_recorded_demo_decodes_and_its_replay_gives_the_same_fused_results(tmp_path):
    recording, replayed = tmp_path / "demo.mcap", tmp_path / "replay.mcap"
    run(tmp_path / "first", "--input", str(DEMO), "--record", str(recording))
    recorded = read(recording)
    audio = recorded["grabber/audio"]
    assert audio[0].format.sample_rate_hz == 16000 and audio[0].payload
    assert all(a.end_ns <= b.start_ns for a, b in itertools.pairwise(audio))  # capture times, in order
    assert {"results/speech", "results/vad", "partials"} <= set(recorded)
    assert len(recorded["results/speech"]) == QUESTIONS
    assert len(utterances(recorded)) == QUESTIONS
    assert {"asr", "vad", "grabber"} <= {event["name"] for event in recorded["components"] if "name" in event}

    done = run(tmp_path / "second", "--input", str(recording), "--record", str(replayed), "--diff")
    assert f"diff: {QUESTIONS} recorded utterances, {QUESTIONS} replayed, 0 differences" in done.stdout
    assert utterances(read(replayed)) == utterances(recorded)
    compared = esiaf("mcap", "diff", str(recording), str(replayed))
    assert compared.returncode == 0, compared.stdout + compared.stderr


def test_a_recording_of_two_streams_replays_both_each_as_a_stream_of_its_own(tmp_path):
    """Two inputs recorded (the demo, and its first 11 s: fewer questions), the recording replayed:
    each recorded stream is played as a stream of its own and diffed against its own recording."""
    samples, rate = soundfile.read(str(DEMO), dtype="int16")
    shorter = tmp_path / "shorter.wav"
    soundfile.write(str(shorter), samples[:11 * rate], rate)
    recording = tmp_path / "two.mcap"
    lean = ("--without", "emotion,gender,voiceid")
    run(tmp_path / "first", "--input", str(DEMO), "--input", str(shorter), *lean, "--record", str(recording))
    recorded = read(recording)
    latest = {fused.id: fused for fused in recorded["fused"]}  # revisions of one id share its stream
    spoken = {stream: sum(f.stream_id == stream for f in latest.values())
              for stream in {chunk.stream_id for chunk in recorded["grabber/audio"]}}
    assert len(spoken) == 2 and sorted(spoken.values())[1] == QUESTIONS and 0 < sorted(spoken.values())[0] < QUESTIONS

    replayed = tmp_path / "replayed.mcap"
    done = run(tmp_path / "second", "--input", str(recording), *lean, "--diff", "--record", str(replayed))
    compared = esiaf("mcap", "diff", str(recording), str(replayed))
    assert compared.returncode == 0, compared.stdout + compared.stderr
    for output in (done.stdout, compared.stdout):
        for stream, count in spoken.items():
            header = next(n for n, line in enumerate(output.splitlines()) if line.startswith(f"stream {stream} "))
            summary = next(line for line in output.splitlines()[header:] if line.startswith("diff:"))
            assert summary == f"diff: {count} recorded utterances, {count} replayed, 0 differences", output
    assert done.stderr.count("esiaf: playing ") == 2, done.stderr


def test_a_recording_rotates_into_files_each_readable(tmp_path):
    recording = tmp_path / "rotated.mcap"
    run(tmp_path / "work", "--input", str(DEMO), "--without", "emotion,gender,voiceid", "--record", str(recording),
        "--record-max-mb", "0.1")
    count = len(list(tmp_path.glob("rotated*.mcap")))
    parts = [recording, *(tmp_path / f"rotated-{n}.mcap" for n in range(2, count + 1))]  # in the order written
    assert count >= 3 and all(part.exists() for part in parts), list(tmp_path.iterdir())
    chunks = [read(part).get("grabber/audio", []) for part in parts]
    assert all(chunks)  # every part holds audio of its own
    played = [chunk for part in chunks for chunk in part]
    assert all(a.sequence + 1 == b.sequence for a, b in itertools.pairwise(played))  # none lost between


def test_a_full_disk_stops_the_recording_not_the_pipeline(tmp_path):
    done = run(tmp_path / "work", "--input", str(DEMO), "--without", "emotion,gender,voiceid", "--record", "/dev/full")
    assert sum(line.startswith("[") for line in done.stdout.splitlines()) == QUESTIONS
    stopped = [line for line in done.stderr.splitlines() if "recording stopped" in line]
    assert len(stopped) == 1 and "No space left on device" in stopped[0]


@pytest.mark.parametrize("content", [b"just some text\n", "truncated"])
def test_an_mcap_that_is_truncated_or_not_mcap_is_one_line_and_exit_2(tmp_path, content):
    bad = tmp_path / "session.mcap"
    if content == "truncated":
        whole = tmp_path / "whole.mcap"
        with whole.open("wb") as handle, Writer(handle) as writer:  # written by the mcap package itself, then cut
            for n in range(100):
                writer.write_message("grabber/audio", pb.AugmentedAudio(sequence=n + 1, payload=b"\0" * 3200),
                                     log_time=n)
        content = whole.read_bytes()[: whole.stat().st_size // 2]
    bad.write_bytes(content)
    done = esiaf("run", "--input", str(bad), "--fast", "--port", str(free_port()), "--workdir", str(tmp_path / "w"))
    assert done.returncode == 2
    assert len(done.stderr.splitlines()) == 1 and str(bad) in done.stderr, done.stderr
    assert not (tmp_path / "w").exists()  # refused before anything started


def test_a_recording_is_never_written_over(tmp_path):
    kept = tmp_path / "kept.mcap"
    kept.write_bytes(b"an earlier recording")
    for command in (["run", "--input", str(DEMO), "--record", str(kept), "--port", str(free_port()), "--workdir",
                     str(tmp_path / "w")], ["record", "--out", str(kept), "--url", "http://127.0.0.1:9"]):
        done = esiaf(*command)
        assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and "exists" in done.stderr, done.stderr
    assert kept.read_bytes() == b"an earlier recording"


def test_esiaf_record_attaches_to_a_running_orchestrator(tmp_path):
    pipeline = Launcher(["--input", str(DEMO), "--grammar", "robocup", "--without", "emotion,gender,voiceid",
                         "--json", "--serve"], tmp_path / "work")
    recording = tmp_path / "attached.mcap"
    try:
        poll(lambda: httpx.get(f"{pipeline.url}/health").status_code == 200, 60)
        recorder = subprocess.Popen([sys.executable, "-m", "esiaf", "record", "--out", str(recording), "--url",
                                     pipeline.url, "--token-file", str(tmp_path / "work" / "token")],
                                    cwd=REPO, stderr=subprocess.PIPE, text=True)
        # the demo plays in real time: the recorder hears its later questions
        pipeline.wait_for_line(lambda line: "is mark zuckerberg" in str(line), 120)
        recorder.send_signal(signal.SIGTERM)
        assert recorder.wait(timeout=60) == 0, recorder.stderr.read() if recorder.stderr else ""
    finally:
        pipeline.stop()
    messages = read(recording)
    assert messages["grabber/audio"] and messages["fused"]
    assert utterances(messages)[-1][0] == "is mark zuckerberg a robot"

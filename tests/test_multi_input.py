"""Several inputs at once under ``esiaf run``: each ``--input`` (or each sound file of a
folder) is played by a grabber instance of its own as a stream of its own; every stream gets its own
sentences and its own stream_end, and the run ends once all have ended; ``--replicas asr=2`` shares
them between two recognisers. ``--serve`` never ends the run on its own: SIGTERM does, cleanly. Bad
inputs fail before any service starts."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter

import httpx
import psutil
import pytest

from esiaf.tools.testing import REPO, need_flite, normalise, shared_data

pytestmark = pytest.mark.e2e
sys.path.insert(0, str(REPO / "scripts"))
ROBOTS = {"robot1": ((2, 11), "slt", 1.0), "robot2": ((37, 5), "awb", 1.3),  # questions, voice, gap
          "robot3": ((23, 14), "slt", 0.8), "robot4": ((30, 41), "awb", 1.1)}
RUN = ("--grammar", "robocup", "--without", "emotion,gender,voiceid,ssl")


def synthesise(folder, names):
    """A WAV per robot in ``folder``, each its own questions in its own voice; the sentences of each."""
    need_flite()
    from synth_questions import read_questions, synthesise_to_wav

    table = read_questions(shared_data("robocup/questions.tsv"))
    folder.mkdir(exist_ok=True)
    truth = {}
    for name in names:
        questions, voice, gap_s = ROBOTS[name]
        said = synthesise_to_wav([(i, table[i]) for i in questions], folder / f"{name}.wav", voice=voice,
                                 gap_s=gap_s)
        truth[name] = [normalise(t.text) for t in said]
    return truth


def streams_played(run) -> dict[str, str]:
    """robot name (the file's stem) -> its stream id, from the launcher's 'playing X as stream Y'."""
    found = re.findall(r"playing \S*/(\w+)\.wav as stream (\S+)", "".join(run.stderr))
    return dict(found)


def finished(run, timeout_s: float) -> int:
    try:
        return run.process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"esiaf run did not end in {timeout_s} s; {run.describe()}") from None


def test_two_inputs_are_two_streams_each_with_its_own_sentences_and_end(launch, tmp_path):
    truth = synthesise(tmp_path / "wavs", ["robot1", "robot2"])
    run = launch("--input", str(tmp_path / "wavs" / "robot1.wav"), "--input", str(tmp_path / "wavs" / "robot2.wav"),
                 "--fast", "--json", *RUN)
    assert finished(run, 150) == 0, run.describe()
    ids = streams_played(run)
    assert sorted(ids) == ["robot1", "robot2"] and len(set(ids.values())) == 2, run.describe()
    assert all(stream_id.startswith(f"{name}-") for name, stream_id in ids.items())
    for name, stream_id in ids.items():
        mine = [line for line in run.lines if line.get("stream_id") == stream_id]
        assert mine[0]["type"] == "stream_start" and mine[-1]["type"] == "stream_end", mine
        assert sum(line["type"] == "stream_end" for line in mine) == 1
        heard = [normalise(line["anchor"]["speech"]["hypotheses"][0]["text"]) for line in mine
                 if line["type"] == "fused_result" and line["revision"] == 1]
        assert heard == truth[name], (name, heard, run.describe())
    assert all(line.get("stream_id") in ids.values() for line in run.lines), run.lines
    logs = run.workdir / "logs"
    assert (logs / "grabber-1.log").exists() and (logs / "grabber-2.log").exists()
    assert not (logs / "grabber.log").exists()


def test_a_folder_of_four_is_four_streams_at_once_each_line_naming_its_stream(launch, tmp_path):
    folder = tmp_path / "robots"
    truth = synthesise(folder, ["robot1", "robot2", "robot3", "robot4"])
    (folder / "notes.txt").write_text("not a sound file: left out")
    run = launch("--input", str(folder), "--fast", *RUN)
    assert finished(run, 180) == 0, run.describe()
    ids = streams_played(run)
    assert sorted(ids) == ["robot1", "robot2", "robot3", "robot4"], run.describe()
    stderr = "".join(run.stderr)
    for n, name in enumerate(sorted(ids), start=1):  # sorted by name, grabber-1 playing the first
        assert f"{name}.wav as stream {ids[name]} (grabber-{n})" in stderr
        assert f"stream {ids[name]} ended, {len(truth[name])} fused result(s)" in stderr, stderr
    texts = [line["text"] for line in run.lines]
    for name, stream_id in ids.items():
        mine = [text.removeprefix(f"[{stream_id}] ") for text in texts if text.startswith(f"[{stream_id}] ")]
        heard = [normalise(m.group(1)) for text in mine if (m := re.search(r"'(.*)' \(p=", text))]
        assert heard == truth[name], (name, texts, stderr)
    assert len(texts) == sum(len(said) for said in truth.values()), texts  # each line belongs to a stream


def test_replicas_of_the_recogniser_each_serve_streams_of_their_own(launch, tmp_path):
    truth = synthesise(tmp_path / "wavs", ["robot1", "robot2", "robot3"])
    run = launch("--input", str(tmp_path / "wavs"), "--replicas", "asr=2", "--fast", "--json", *RUN)
    assert finished(run, 150) == 0, run.describe()
    ids = streams_played(run)
    served_by = {}
    for name, stream_id in ids.items():
        mine = [line for line in run.lines if line.get("type") == "fused_result" and line["stream_id"] == stream_id]
        heard = [normalise(line["anchor"]["speech"]["hypotheses"][0]["text"]) for line in mine
                 if line["revision"] == 1]
        assert heard == truth[name], (name, heard, run.describe())  # announced ahead: nothing missed with --fast
        served_by[name] = {line["anchor"]["instance"] for line in mine}
    # each stream by one instance, balanced: the least loaded takes the next (which comes first depends on
    # which instance registered first)
    assert all(len(instances) == 1 for instances in served_by.values()), served_by
    assert sorted(Counter(i for instances in served_by.values() for i in instances).items(), key=lambda x: x[1]) \
        in ([("asr-2", 1), ("asr-1", 2)], [("asr-1", 1), ("asr-2", 2)]), served_by
    logs = run.workdir / "logs"
    assert (logs / "asr-1.log").exists() and (logs / "asr-2.log").exists() and not (logs / "asr.log").exists()
    assert "asr as 2 instances sharing the streams" in "".join(run.stderr)


def test_serve_keeps_every_service_up_after_the_streams_ended_until_sigterm(launch, tmp_path):
    synthesise(tmp_path / "wavs", ["robot1", "robot2"])
    run = launch("--input", str(tmp_path / "wavs" / "robot1.wav"), "--input", str(tmp_path / "wavs" / "robot2.wav"),
                 "--fast", "--json", "--serve", *RUN)
    deadline = time.monotonic() + 150
    while sum(line.get("type") == "stream_end" for line in run.lines) < 2:
        assert time.monotonic() < deadline and run.process.poll() is None, run.describe()
        time.sleep(0.2)
    services = [p for p in psutil.Process(run.process.pid).children() if "esiaf_services." in " ".join(p.cmdline())]
    time.sleep(8)  # both streams over, both grabbers done: still serving
    assert run.process.poll() is None, run.describe()
    assert httpx.get(f"{run.url}/health", timeout=5).status_code == 200
    alive = [p for p in services if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert {p.cmdline()[2] for p in alive} >= {f"esiaf_services.{name}" for name in ("orchestrator", "asr", "vad")}
    run.process.send_signal(signal.SIGTERM)
    assert finished(run, 30) == 0, run.describe()
    assert "stopped (SIGTERM)" in "".join(run.stderr)
    assert not [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


def esiaf_run(tmp_path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf", "run", "--workdir", str(tmp_path / "wd"), *args],
                          cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                          capture_output=True, text=True, timeout=60)


def test_bad_inputs_fail_with_a_clear_message_before_anything_starts(tmp_path):
    wav = REPO / "examples" / "robocup_questions.wav"
    (tmp_path / "empty").mkdir()
    (tmp_path / "papers").mkdir()
    (tmp_path / "papers" / "notes.txt").write_text("no sound here")
    cases = {
        ("--input", str(wav), "--input", str(tmp_path / "nope.wav")): "input file " + str(tmp_path / "nope.wav")
        + " does not exist",
        ("--input", str(tmp_path / "empty")): f"input folder {tmp_path / 'empty'} is empty",
        ("--input", str(tmp_path / "papers")): f"input folder {tmp_path / 'papers'} holds no sound file",
        ("--input", str(wav), "--input", str(wav), "--stream-id", "one"):
            "--stream-id names the stream of a single input, not of 2",
        ("--input", str(wav), "--replicas", "asr=0"): "--replicas takes SERVICE=N with N from 1 to 8",
        ("--input", str(wav), "--replicas", "asr=9"): "--replicas takes SERVICE=N with N from 1 to 8",
        ("--input", str(wav), "--replicas", "asr"): "--replicas takes SERVICE=N",
        ("--input", str(wav), "--replicas", "emotion=2", "--without", "emotion"):
            "--replicas emotion=2: emotion is not an analyser this run starts on the VAD's output or a plug-in "
            "(asr, gender, voiceid)",
        ("--input", str(wav), "--replicas", "orchestrator=2"): "--replicas orchestrator=2: orchestrator is not",
    }
    for args, message in cases.items():
        result = esiaf_run(tmp_path, *args)
        assert result.returncode == 2, (args, result.stderr)
        assert result.stderr.startswith(f"esiaf: {message}"), (args, result.stderr)
        assert "Traceback" not in result.stderr
        assert not (tmp_path / "wd").exists(), args  # no service started, nothing written

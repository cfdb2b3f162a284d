"""Faults under ``esiaf run``: a service killed with SIGKILL mid-stream is restarted and
the pipeline goes on; the orchestrator comes back on the same ZeroMQ ports and the launcher's
websocket resumes with after_seq, so only what was in flight is missing."""
from __future__ import annotations

import os
import signal
import sys
import time

import httpx
import psutil
import pytest

from esiaf.tools.testing import REPO, is_spare, need_flite, normalise, poll, shared_data

pytestmark = pytest.mark.e2e
sys.path.insert(0, str(REPO / "scripts"))
QUESTIONS = (2, 11, 23, 37, 5, 14, 30, 41)


@pytest.fixture
def questions(tmp_path):
    need_flite()
    from synth_questions import read_questions, synthesise_to_wav

    table = read_questions(shared_data("robocup/questions.tsv"))
    wav = tmp_path / "questions.wav"
    truth = synthesise_to_wav([(i, table[i]) for i in QUESTIONS], wav, gap_s=3.0)
    return wav, [normalise(t.text) for t in truth]


def service_pid(launcher, name: str) -> int | None:
    for child in psutil.Process(launcher.process.pid).children(recursive=True):
        try:
            if f"esiaf_services.{name}" in child.cmdline() and not is_spare(child):
                return child.pid
        except psutil.Error:
            continue
    return None


def fused_texts(launcher) -> list[str]:
    """The text of each fused result as it finally stands (its latest revision), in publication order.
    A revision is not a double: a result later than its timeout (under load, after a restart) revises."""
    latest = {}
    for line in launcher.lines:
        if line.get("type") == "fused_result" and line.get("anchor", {}).get("speech", {}).get("hypotheses"):
            latest.setdefault(line["id"], {})[line["revision"]] = line["anchor"]["speech"]["hypotheses"][0]["text"]
    # "speech not understood" (an empty text: esiaf_services/asr/README.md) is not a sentence heard
    return [normalise(text) for by_revision in latest.values() if (text := by_revision[max(by_revision)])]


@pytest.mark.parametrize("victim", ["asr", "orchestrator"])
def test_a_service_killed_mid_stream_comes_back_and_the_pipeline_goes_on(launch, questions, victim):
    wav, truth = questions
    run = launch("--input", str(wav), "--grammar", "robocup", "--json", "--without", "emotion,gender",
                 "--stream-id", f"kill-{victim}")
    run.wait_for_line(lambda line: line.get("type") == "fused_result", timeout_s=120)  # the first question
    first_pid = service_pid(run, victim)
    listed = httpx.get(f"{run.url}/components", headers=run.headers, timeout=5).json()["items"]
    killed_id = next((c["component_id"] for c in listed if c.get("pid") == first_pid), None)
    os.kill(first_pid, signal.SIGKILL)
    killed_at = time.monotonic()
    if killed_id is not None:  # an analyser: its launcher reports it dead at once, no dead_after_s (2.5 s) wait
        poll(lambda: any(c["component_id"] == killed_id and c["status"] == "dead" for c in httpx.get(
            f"{run.url}/components", params={"include_dead": True}, headers=run.headers, timeout=5).json()["items"]),
             timeout_s=5)
        assert time.monotonic() - killed_at < 1.5, run.describe()
    try:
        poll(lambda: (service_pid(run, victim) or first_pid) != first_pid, timeout_s=30)  # restarted
    except AssertionError as exc:
        raise AssertionError(f"{victim} not restarted: {exc}; {run.describe()}") from None
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)
    assert run.stop() in (0, 130)
    stderr = "".join(run.stderr)
    assert f"service {victim} killed by SIGKILL" in stderr and "restarting it" in stderr
    heard = fused_texts(run)
    # only the question in flight while it was down may be missing; nothing else is lost or doubled
    assert len(heard) >= len(truth) - 2, (heard, stderr)
    assert heard == [t for t in truth if t in heard]
    assert heard[-1] == truth[-1]
    firsts = [line["id"] for line in run.lines if line.get("type") == "fused_result" and line["revision"] == 1]
    assert firsts == sorted(set(firsts))  # the resumed websocket neither repeated nor reordered one


def test_a_killed_vad_is_replaced_by_its_waiting_spare(launch, questions):
    """The launcher keeps a spare vad, imported and waiting; when the vad dies the spare takes over (a
    registration instead of a whole start) and the launcher starts a new spare later."""
    wav, truth = questions
    run = launch("--input", str(wav), "--grammar", "robocup", "--json", "--without", "emotion,gender,voiceid",
                 "--stream-id", "spare")
    launcher = psutil.Process(run.process.pid)
    spare = poll(lambda: next((c for c in launcher.children() if is_spare(c) is True and c.is_running()
                               and "esiaf_services.vad" in c.cmdline()), None), timeout_s=90)
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=60)  # the spare is there first
    vad = service_pid(run, "vad")
    assert vad is not None and vad != spare.pid
    os.kill(vad, signal.SIGKILL)
    registered = poll(lambda: next((c["pid"] for c in httpx.get(
        f"{run.url}/components", headers=run.headers, timeout=10).json()["items"]
        if c["name"] == "vad" and c.get("pid") not in (None, vad)), None), timeout_s=60)
    assert registered == spare.pid, run.describe()  # the spare, not a new process
    assert not is_spare(spare)  # it says it is the vad now
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)
    assert run.stop() in (0, 130)
    assert "service vad killed by SIGKILL" in "".join(run.stderr)
    assert "--- esiaf: restart 1 (its spare) ---" in (run.workdir / "logs" / "vad.log").read_text()
    heard = fused_texts(run)
    assert len(heard) >= len(truth) - 2, (heard, run.describe())  # what was in flight at most
    assert heard == [t for t in truth if t in heard]

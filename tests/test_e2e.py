"""End to end: every service as a process, real audio, fused results over a real websocket."""
from __future__ import annotations

import json
import sys

import psutil
import pytest
from websockets.sync.client import connect

from esiaf.tools.testing import REPO, need_flite, normalise, shared_data

pytestmark = pytest.mark.e2e
SPAN_TOLERANCE_S = 0.150

sys.path.insert(0, str(REPO / "scripts"))


def collect_fused(run, stream_id: str, timeout_s: float) -> list[dict]:
    """Every fused result of a stream, from a websocket client of our own, until its stream_end."""
    fused = []
    with connect(run.ws_url(f"/ws/fused?stream={stream_id}&after_id=0"), open_timeout=10) as ws:
        while True:
            message = json.loads(ws.recv(timeout=timeout_s))
            if message["type"] == "stream_end":
                return fused
            fused.append(message)


def best_text(fused: dict) -> str:
    return fused["anchor"]["speech"]["hypotheses"][0]["text"]


def test_robocup_questions_in_order_with_spans_where_the_speech_is(launch, tmp_path):
    need_flite()
    questions_file = shared_data("robocup/questions.tsv")
    from synth_questions import read_questions, synthesise_to_wav

    questions = read_questions(questions_file)
    chosen = [(i, questions[i]) for i in (2, 11, 23, 37)]
    wav = tmp_path / "questions.wav"
    truth = synthesise_to_wav(chosen, wav, gap_s=2.0)

    run = launch("--input", str(wav), "--grammar", "robocup", "--json", "--serve", "--stream-id", "e2e-questions")
    start = run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=90)
    fused = collect_fused(run, "e2e-questions", timeout_s=60)

    assert [normalise(best_text(f)) for f in fused] == [normalise(t.text) for t in truth]
    for f, t in zip(fused, truth, strict=True):
        span = f["anchor"]["span"]
        assert abs((span["start_ns"] - start["start_ns"]) / 1e9 - t.start_s) < SPAN_TOLERANCE_S, (f, t)
        assert abs((span["end_ns"] - start["start_ns"]) / 1e9 - t.end_s) < SPAN_TOLERANCE_S, (f, t)
        assert f["completion"] == "complete" and f["revision"] == 1
    # the launcher's own websocket client printed the same results
    printed = [line for line in run.lines if line.get("type") == "fused_result"]
    assert [p["id"] for p in printed] == [f["id"] for f in fused]

    children = psutil.Process(run.process.pid).children(recursive=True)
    assert run.stop() in (0, 130)
    _gone, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, f"orphaned: {alive}"


def test_goforward_raw_played_fast_then_the_launcher_exits_by_itself(launch):
    raw = shared_data("speech/pocketsphinx/goforward.raw")
    run = launch("--input", str(raw), "--fast", "--json")
    assert run.process.wait(timeout=120) == 0, "".join(run.stderr)
    fused = [line for line in run.lines if line.get("type") == "fused_result"]
    assert [best_text(f) for f in fused] == ["go forward ten meters"]
    start = next(line for line in run.lines if line.get("type") == "stream_start")
    span = fused[0]["anchor"]["span"]
    assert 0.0 <= (span["start_ns"] - start["start_ns"]) / 1e9 < (span["end_ns"] - start["start_ns"]) / 1e9 <= 3.0
    assert run.lines[-1]["type"] == "stream_end"

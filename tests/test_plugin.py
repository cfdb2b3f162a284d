"""An analyser in one folder: a Duration analyser, written into a folder
outside the repository and run with ``esiaf run --with``, reaches the fused results, the websocket
and /results, and no file of the repository changes."""
from __future__ import annotations

import json
import subprocess

import httpx
import pytest
from websockets.sync.client import connect

from esiaf.tools.testing import REPO

pytestmark = pytest.mark.e2e

DURATION = '''\
from esiaf import UtteranceComponent, main

class Duration(UtteranceComponent):
    """Seconds of speech in each utterance."""
    service = "duration"
    kind = "duration"

    def analyse(self, samples, rate):
        return {"value": len(samples) / rate}

raise SystemExit(main(Duration))
'''


def repository_state() -> str:
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=REPO,
                          capture_output=True, text=True).stdout


def test_a_plugin_folder_reaches_fused_results_websocket_and_results(launch, tmp_path_factory):
    folder = tmp_path_factory.mktemp("my-analysers") / "duration"
    folder.mkdir()
    (folder / "__main__.py").write_text(DURATION)
    before = repository_state()
    run = launch("--input", str(REPO / "examples/robocup_questions.wav"), "--grammar", "robocup", "--fast",
                 "--without", "emotion,gender", "--with", str(folder), "--json", "--serve", "--stream-id", "plug")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)
    fused = [line for line in run.lines if line.get("type") == "fused_result"]
    assert len(fused) == 5
    for line in fused:
        [result] = line["results"]["duration"]
        span = line["anchor"]["span"]
        assert result["type"] == "duration" and result["component"] == "duration"
        assert result["duration"]["value"] == pytest.approx((span["end_ns"] - span["start_ns"]) / 1e9, abs=0.05)
        assert line["aggregates"]["duration"]["value"] == pytest.approx(result["duration"]["value"])
        assert line["completion"] == "complete"
    # the websocket replays them, and /results holds each one
    with connect(run.ws_url("/ws/fused?stream=plug&after_id=0"), open_timeout=10) as ws:
        replayed = [json.loads(ws.recv(timeout=10)) for _ in fused]
    assert [f["results"]["duration"][0]["id"] for f in replayed] == [f["results"]["duration"][0]["id"] for f in fused]
    stored = httpx.get(f"{run.url}/results", params={"type": "duration", "stream": "plug"},
                       headers=run.headers).json()["items"]
    assert len(stored) == 5
    assert repository_state() == before


def test_the_line_shows_a_plugins_value():
    from esiaf.tools.cli import format_line
    line = {"anchor": {"span": {"start_ns": 0, "end_ns": 10**9}, "speech": {"hypotheses": [
        {"text": "hello", "probability": 0.9}]}}, "aggregates": {"duration": {"value": 1.234, "overlap_s": 1}}}
    assert format_line(line, 0) == "[0.00–1.00 s] 'hello' (p=0.90), duration 1.23"


def test_with_something_that_is_no_component_is_one_line(tmp_path):
    import sys
    empty = tmp_path / "empty"
    empty.mkdir()
    for spec, complaint in ((str(empty), "no __main__.py"), ("no_such_analyser_xyz", "not a folder")):
        result = subprocess.run([sys.executable, "-m", "esiaf", "run",
                                 "--input", str(REPO / "examples/robocup_questions.wav"),
                                 "--with", spec, "--workdir", str(tmp_path / "w")], cwd=REPO, capture_output=True,
                                text=True, timeout=60)
        assert result.returncode == 2 and complaint in result.stderr and "Traceback" not in result.stderr


def test_replicas_of_a_plugin_share_the_streams(launch, tmp_path_factory):
    """``--replicas duration=2`` with ``--with``: two instances of the plug-in, each serving a stream
    of its own; every utterance of both streams gets exactly one duration result."""
    import shutil
    folder = tmp_path_factory.mktemp("analysers") / "duration"
    folder.mkdir()
    (folder / "__main__.py").write_text(DURATION)
    wavs = tmp_path_factory.mktemp("wavs")
    for name in ("left", "right"):
        shutil.copy(REPO / "examples/robocup_questions.wav", wavs / f"{name}.wav")
    run = launch("--input", str(wavs), "--grammar", "robocup", "--fast", "--without", "emotion,gender,voiceid",
                 "--with", str(folder), "--replicas", "duration=2", "--json", "--serve")
    ended: set[str] = set()  # stream ids: the file's stem and the run's start time
    run.wait_for_line(lambda line: line.get("type") == "stream_end" and ended.add(line["stream_id"]) is None
                      and len(ended) == 2, timeout_s=240)
    instances = httpx.get(f"{run.url}/components", headers=run.headers).json()["services"]["duration"]["instances"]
    assert sorted(instances) == ["duration-1", "duration-2"]
    served_by = {}
    for stream in ended:
        fused = [line for line in run.lines if line.get("type") == "fused_result" and line["stream_id"] == stream
                 and line["revision"] == 1]
        assert len(fused) == 5, stream
        [served_by[stream]] = {result["instance"] for line in fused for result in line["results"]["duration"]}
        assert all(len(line["results"]["duration"]) == 1 for line in fused)
    assert sorted(served_by.values()) == ["duration-1", "duration-2"]  # a stream each

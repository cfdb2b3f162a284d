"""Partial results while people speak: the recogniser's partials reach ``esiaf run --json --partials``
(the websocket's ``partial`` events) before each utterance's fused result, grow, are closed before
it, never appear in ``/fused`` or ``/results``, and a websocket client that did not ask for them
never sees one. The whole pipeline as processes, real pocketsphinx, real sockets."""
from __future__ import annotations

import json

import httpx
import pytest
from websockets.sync.client import connect

from esiaf.tools.testing import REPO, Launcher

EXAMPLE = REPO / "examples" / "robocup_questions.wav"


@pytest.fixture
def run(tmp_path):
    launcher = Launcher(["--input", str(EXAMPLE), "--grammar", "robocup", "--json", "--partials",
                         "--without", "emotion,gender,voiceid", "--serve"], tmp_path / "work")
    yield launcher
    launcher.process.kill()
    launcher.process.wait(timeout=30)


def test_partials_grow_before_each_fused_result_and_are_never_stored(run):
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=180)
    with connect(run.ws_url("/ws/fused")) as plain:  # did not ask for partials
        run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)
        seen_plain = []
        try:
            while True:
                seen_plain.append(json.loads(plain.recv(timeout=1.0))["type"])
        except TimeoutError:
            pass
    assert "partial" not in seen_plain and "fused_result" in seen_plain
    lines = [line for line in run.lines if line.get("type") in ("partial", "fused_result")]
    fused = [line for line in lines if line["type"] == "fused_result" and line["revision"] == 1]
    assert len(fused) == 5
    # the partials of each utterance: those since the previous fused result
    groups, current = [], []
    for line in lines:
        if line["type"] == "partial":
            current.append(line)
        elif line["revision"] == 1:
            groups.append(current)
            current = []
    with_partials = [group for group in groups if any(not p["closed"] for p in group)]
    assert len(with_partials) >= 3, groups  # the stream's first utterance is decoded whole (pocketsphinx)
    for group, result in zip(groups, fused, strict=True):
        opened = [p for p in group if not p["closed"]]
        if not opened:
            continue
        assert group[-1]["closed"], group  # closed before its fused result arrives
        ends = [p["span"]["end_ns"] for p in opened]
        assert ends == sorted(ends) and len({p["span"]["start_ns"] for p in opened}) == 1  # it grows
        assert opened[0]["span"]["start_ns"] <= result["anchor"]["span"]["end_ns"]
        stables = [len(p["stable"].split()) for p in opened]
        assert all(p["text"].startswith(p["stable"]) for p in opened)
        assert max(stables) <= len(opened[-1]["text"].split())
    headers = run.headers
    stored = httpx.get(f"{run.url}/results", params={"limit": 1000}, headers=headers).json()["items"]
    assert stored and all(r["type"] != "partial" for r in stored)
    published = httpx.get(f"{run.url}/fused", headers=headers).json()["items"]
    assert len(published) == 5 and all(f["type"] == "fused_result" for f in published)

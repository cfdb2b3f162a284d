"""The ssl service as a process on a real 4-channel recording: orchestrator, grabber, ssl, real sockets."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys

from esiaf.tools.testing import REPO, poll, shared_data

NS = 1_000_000_000


def run_service(orchestrator, name: str, *args: str, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", f"esiaf_services.{name}", *args], cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
                                 "ESIAF_STREAM_ID": "mix", **(env or {})},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def all_results(orchestrator, **query) -> list[dict]:
    items, after = [], 0
    while True:
        page = orchestrator.http.get("/results", params={**query, "after_id": after, "limit": 1000}).json()
        items += page["items"]
        if not page["items"]:
            return items
        after = page["next_after_id"]


def test_respeaker_recording_runs_through_ssl_every_frame_covered(orchestrator):
    mix = shared_data("multichannel/odas2_respeaker4/mix.wav")
    ssl = run_service(orchestrator, "ssl", "--array", "respeaker4")
    try:
        poll(lambda: orchestrator.component("ssl"), timeout_s=30)
        grabber = run_service(orchestrator, "grabber", "--input", str(mix), "--fast",
                              env={"ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"})
        assert grabber.wait(timeout=60) == 0, grabber.stdout.read()
        stream = poll(lambda: orchestrator.http.get("/streams/mix").json(), timeout_s=10)
        results = poll(lambda: (r := all_results(orchestrator, type="ssl", stream="mix"))
                       and r[-1]["span"]["end_ns"] - stream["start_ns"] >= 3.9 * NS and r, timeout_s=30)
        # the counters travel with heartbeats (every 0.5 s): they may lag the results a little
        stats = poll(lambda: (s := orchestrator.component("ssl")["stats"]).get("inputs", {}).get(
            "grabber/audio", {}).get("received") and s, timeout_s=10)
    finally:
        ssl.terminate()
        output = ssl.communicate(timeout=20)[0]
    assert ssl.returncode == 0, output

    spans = [(r["span"]["start_ns"] - stream["start_ns"], r["span"]["end_ns"] - stream["start_ns"]) for r in results]
    assert spans[0][0] == 0 and abs(spans[-1][1] - 63184 * NS // 16000) < NS // 1000  # the whole file
    assert all(a[1] == b[0] for a, b in itertools.pairwise(spans)), "ssl results leave gaps or overlap"
    located = [r for r in results if "ssl" in r]
    assert len(located) >= len(results) // 2, "most frames of this recording hold a source"
    assert all("nothing" in r or r["ssl"]["directions"] for r in results)
    for r in located:
        d = r["ssl"]["directions"][0]
        assert 0 <= d["azimuth_deg"] < 360 and 0 <= d["probability"] <= 1 and d["source_id"]
    inputs = stats["inputs"]["grabber/audio"]
    assert inputs["bad"] == 0 and inputs["lost"] == 0 and inputs["received"] > 0

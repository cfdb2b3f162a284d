"""The clock offset estimate on heartbeat round trips (esiaf/clock.py), and a component whose clock
runs 3 s ahead measured by the real orchestrator."""
from __future__ import annotations

import json
import threading

import httpx
import pytest

from esiaf import Component
from esiaf.clock import WINDOW, ClockEstimate
from esiaf.tools.testing import REPO, normalise, poll

S = 10**9
MS = 10**6


def test_the_shortest_round_trip_wins_and_half_of_it_is_the_uncertainty():
    clock = ClockEstimate()
    assert clock.report() is None
    # orchestrator 3 s behind us; a 40 ms round trip queued on the way out, then a clean 4 ms one
    clock.add(sent_ns=100 * S, orchestrator_ns=97 * S + 38 * MS, received_ns=100 * S + 40 * MS)
    assert clock.report() == {"offset_ns": -3 * S + 18 * MS, "uncertainty_ns": 20 * MS}
    clock.add(sent_ns=101 * S, orchestrator_ns=98 * S + 2 * MS, received_ns=101 * S + 4 * MS)
    assert clock.report() == {"offset_ns": -3 * S, "uncertainty_ns": 2 * MS}
    clock.add(sent_ns=102 * S, orchestrator_ns=99 * S, received_ns=101 * S)  # received before sent: not a sample
    clock.add(sent_ns=102 * S, orchestrator_ns=99 * S, received_ns=200 * S)  # an answer 98 s late: neither
    assert clock.report() == {"offset_ns": -3 * S, "uncertainty_ns": 2 * MS}


def test_old_samples_leave_the_window():
    clock = ClockEstimate()
    clock.add(0, 5 * S, 0)  # a perfect sample of a clock that has since been set
    for i in range(WINDOW):
        clock.add(i * S, i * S + 10 * MS, i * S + 20 * MS)
    assert clock.report() == {"offset_ns": 0, "uncertainty_ns": 10 * MS}


class Idle(Component):
    """Does nothing but beat."""
    service = "idle"


def test_the_orchestrator_shows_a_component_clock_3_s_ahead(orchestrator):
    idle = Idle(Idle.Settings(name="idle", orchestrator_url=orchestrator.url, clock_skew_s=3.0))
    thread = threading.Thread(target=idle.run, daemon=True)
    thread.start()
    try:
        shown = poll(lambda: (c := orchestrator.component("idle")) and c["clock_offset_ms"] is not None and c,
                     timeout_s=10)
        assert abs(shown["clock_offset_ms"] + 3000) <= shown["clock_uncertainty_ms"] + 5, shown
        assert 0 <= shown["clock_uncertainty_ms"] < 100, shown
    finally:
        idle.stop()
        thread.join(timeout=10)


@pytest.mark.e2e
@pytest.mark.parametrize("skew_s", [-3.0, 3.0], ids=["behind", "ahead"])
def test_a_microphone_host_whose_clock_is_3_s_off_still_gets_complete_results(launch, skew_s):
    """The grabber stamps capture times with a clock 3 s off the orchestrator's, played in real time:
    every question is still fused complete (no deadline long gone on arrival, nor 3 s late), with
    its emotion, gender and voice, and the grabber's offset is shown."""
    truth = [s["text"] for s in json.loads((REPO / "examples/robocup_questions.json").read_text())["sentences"]]
    run = launch("--input", str(REPO / "examples/robocup_questions.wav"), "--grammar", "robocup", "--json",
                 "--serve", env={"ESIAF_GRABBER_CLOCK_SKEW_S": str(skew_s)})
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=120)

    def grabber() -> dict | None:  # while it plays: it leaves at the end of the file
        items = httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]
        return next((c for c in items if c["name"] == "grabber" and c["clock_offset_ms"] is not None), None)

    shown = poll(grabber, timeout_s=10)
    assert abs(shown["clock_offset_ms"] + skew_s * 1000) <= shown["clock_uncertainty_ms"] + 5, shown
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    firsts = [line for line in run.lines if line.get("type") == "fused_result" and line["revision"] == 1]
    assert sorted(normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in firsts) == \
        sorted(normalise(t) for t in truth)
    assert all(f["completion"] == "complete" and f["aggregates"]["emotion"] for f in firsts), \
        [(f["completion"], f["missing"], f["aggregates"]["emotion"]) for f in firsts]
    assert all(0 <= f["anchor"]["latency_ms"] < 1000 for f in firsts), [f["anchor"]["latency_ms"] for f in firsts]

"""A second robot joins a running pipeline: its grabber registers under the same name
as the first (another instance, not a replacement; the two replaced each other every heartbeat
before), both streams get their own sentences, and every fused result of both is complete with
its emotion and gender. (That an analyser which has not covered a stream yet is waited for, never
assumed done, is test_fusion_units.py::test_a_second_stream_waits_for_an_analyser_that_has_not_covered_it_yet:
here the emotion service usually answers before the asr.)"""
from __future__ import annotations

import os
import subprocess
import sys

import httpx
import pytest
from test_e2e import best_text, collect_fused

from esiaf.tools.testing import REPO, need_flite, normalise, poll, shared_data

pytestmark = pytest.mark.e2e
sys.path.insert(0, str(REPO / "scripts"))


def test_a_second_grabber_of_the_same_name_streams_beside_the_first_with_complete_results(launch, tmp_path):
    need_flite()
    from synth_questions import read_questions, synthesise_to_wav

    table = read_questions(shared_data("robocup/questions.tsv"))
    first = synthesise_to_wav([(i, table[i]) for i in (2, 11, 23)], tmp_path / "robot1.wav", gap_s=1.5)
    second = synthesise_to_wav([(i, table[i]) for i in (37, 5)], tmp_path / "robot2.wav", voice="awb",
                               lead_in_s=0.3, gap_s=1.3)
    run = launch("--input", str(tmp_path / "robot1.wav"), "--grammar", "robocup", "--json", "--serve",
                 "--without", "voiceid", "--stream-id", "robot1")
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=120)
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": run.url, "ESIAF_TOKEN": run.token}
    robot2 = subprocess.Popen([sys.executable, "-m", "esiaf_services.grabber", "--input", str(tmp_path / "robot2.wav"),
                               "--set", "stream_id=robot2"], cwd=REPO, env=env,  # the same name: grabber
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        def grabbers() -> list[str]:
            services = httpx.get(f"{run.url}/components", headers=run.headers).json()["services"]
            return services.get("grabber", {}).get("instances", [])
        poll(lambda: len(grabbers()) == 2, timeout_s=30)  # neither replaced the other
        fused2 = [f for f in collect_fused(run, "robot2", timeout_s=120) if f["revision"] == 1]
        run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=90)  # robot1's, as printed
        fused1 = [line for line in run.lines if line.get("type") == "fused_result" and line["revision"] == 1]
    finally:
        robot2.terminate()
        robot2.wait(timeout=10)
    assert [normalise(best_text(f)) for f in fused1] == [normalise(t.text) for t in first]
    assert [normalise(best_text(f)) for f in fused2] == [normalise(t.text) for t in second]
    for fused in fused1 + fused2:  # complete means every analyser answered for this stream
        assert fused["completion"] == "complete", fused
        assert fused["results"]["emotion"] and fused["results"]["gender"], fused

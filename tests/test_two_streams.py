"""Two robots at once: a second grabber streams into a running ``esiaf run --serve``;
the asr keeps one decoder per stream, so each stream gets its own sentences and its own end."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_e2e import best_text, collect_fused

from esiaf.tools.testing import REPO, need_flite, normalise, shared_data

pytestmark = pytest.mark.e2e
sys.path.insert(0, str(REPO / "scripts"))


@pytest.mark.parametrize("backend", ["pocketsphinx", "whisper"])
def test_two_streams_at_once_each_get_their_own_sentences(launch, tmp_path, backend):
    need_flite()
    if backend == "whisper":
        pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from synth_questions import read_questions, synthesise_to_wav

    table = read_questions(shared_data("robocup/questions.tsv"))
    first = synthesise_to_wav([(i, table[i]) for i in (2, 11, 23)], tmp_path / "robot1.wav", gap_s=1.0)
    second = synthesise_to_wav([(i, table[i]) for i in (37, 5, 14)], tmp_path / "robot2.wav", voice="awb",
                               lead_in_s=0.3, gap_s=1.3)
    run = launch("--input", str(tmp_path / "robot1.wav"), "--grammar", "robocup", "--json", "--serve",
                 "--without", "emotion,gender,voiceid", "--stream-id", "robot1", "--asr", backend)
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=120)
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": run.url, "ESIAF_TOKEN": run.token}
    robot2 = subprocess.Popen([sys.executable, "-m", "esiaf_services.grabber", "--input", str(tmp_path / "robot2.wav"),
                               "--set", "name=grabber2", "--set", "stream_id=robot2"], cwd=REPO, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        heard2 = [normalise(best_text(f)) for f in collect_fused(run, "robot2", timeout_s=90) if f["revision"] == 1]
        run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=90)  # robot1's, as printed
        heard1 = [normalise(line["anchor"]["speech"]["hypotheses"][0]["text"]) for line in run.lines
                  if line.get("type") == "fused_result" and line["revision"] == 1]
    finally:
        robot2.terminate()
        robot2.wait(timeout=10)
    assert heard1 == [normalise(t.text) for t in first]
    assert heard2 == [normalise(t.text) for t in second]

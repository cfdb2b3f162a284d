"""`esiaf eval robocup`: the harness on two short runs through the real pipeline, and its bad options."""
import subprocess
import sys

import pytest

from esiaf.tools.testing import REPO, free_port, need_flite, shared_data

pytestmark = pytest.mark.e2e


def run_eval(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "esiaf", "eval", "robocup", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def test_two_runs_at_10_db_recognise_most_questions_with_their_directions(tmp_path):
    need_flite()
    shared_data("robocup/questions.tsv")
    shared_data("noise/speech_commands_bg/doing_the_dishes.wav")
    done = run_eval("--runs", "1", "--snr", "10:10", "--seed", "7", "--workdir", str(tmp_path),
                    "--port", str(free_port()))
    assert done.returncode == 0, done.stderr
    figures = dict(line.split("=", 1) for line in done.stdout.splitlines() if "=" in line and " " not in line)
    assert figures["runs"] == "2" and figures["questions"] == "20" and figures["failed_runs"] == "0"
    assert "[2/2]" in done.stderr  # progress, run by run
    assert float(figures["questions_recognised"]) >= 0.5, done.stdout
    assert float(figures["ssl_within_15"]) >= 0.7, done.stdout
    assert float(figures["spurious_per_run"]) <= 2, done.stdout
    assert 0 <= float(figures["oracle_questions_recognised"]) <= 1
    assert "thesis (Pepper)" in done.stdout and "oracle" in done.stdout
    assert (tmp_path / "pepper4-run1" / "scene.json").is_file()


@pytest.mark.parametrize("args, message", [
    (["--runs", "0"], "--runs must be from 1 to 1000"),
    (["--snr", "15:5"], "--snr 15:5: need"),
    (["--snr", "loud"], "--snr takes LOW:HIGH"),
    (["--array", "nowhere.yaml"], "nowhere.yaml"),
    (["--port", "70000"], "--port must be"),
    (["--vocabulary"], "--vocabulary and --free go with --task gpsr"),
])
def test_options_out_of_range_are_one_clear_line(args, message):
    done = run_eval(*args, timeout=60)
    assert done.returncode == 2
    assert message in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_a_run_whose_pipeline_fails_is_reported_and_scored_as_answering_nothing(tmp_path):
    need_flite()
    shared_data("robocup/questions.tsv")
    shared_data("noise/speech_commands_bg/doing_the_dishes.wav")
    done = run_eval("--runs", "1", "--array", "respeaker4", "--no-oracle", "--workdir", str(tmp_path),
                    "--port", str(free_port()), "--", "--chunk-ms", "0")  # the grabber refuses it
    assert done.returncode == 0, done.stderr
    assert "respeaker4-run1: esiaf run exited with 2" in done.stderr and "Traceback" not in done.stderr
    figures = dict(line.split("=", 1) for line in done.stdout.splitlines() if "=" in line and " " not in line)
    assert figures["failed_runs"] == "1" and float(figures["questions_recognised"]) == 0

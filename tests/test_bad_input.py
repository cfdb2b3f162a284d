"""Bad input gives one clear message naming the thing, never a traceback, and kills nothing else."""
from __future__ import annotations

import os
import socket
import subprocess
import sys

import httpx

from esiaf.tools.testing import REPO, free_port, poll

ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def esiaf_run(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf", "run", *args], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout_s)


def assert_clear(result: subprocess.CompletedProcess, *phrases: str) -> None:
    assert result.returncode != 0
    assert "Traceback" not in result.stderr.split("ends:")[0], result.stderr
    for phrase in phrases:
        assert phrase in result.stderr, result.stderr


def test_missing_input_file(tmp_path):
    result = esiaf_run("--input", str(tmp_path / "nope.wav"), "--workdir", str(tmp_path))
    assert_clear(result, "nope.wav does not exist")
    assert result.returncode == 2


def test_unreadable_input_file(tmp_path):
    bad = tmp_path / "noise.wav"
    bad.write_bytes(b"this is not a wav file")
    assert_clear(esiaf_run("--input", str(bad), "--workdir", str(tmp_path)), "cannot read input file", "noise.wav")


def test_port_in_use(tmp_path):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        result = esiaf_run("--input", str(REPO / "examples" / "robocup_questions.wav"), "--port", str(port),
                           "--workdir", str(tmp_path))
    assert_clear(result, f"cannot listen on 127.0.0.1:{port}")


def test_malformed_grammar_names_the_file_and_the_service(tmp_path):
    grammar = tmp_path / "broken.gram"
    grammar.write_text("#JSGF V1.0;\ngrammar broken;\npublic <s> = ( go | ;\n")
    result = esiaf_run("--input", str(REPO / "examples" / "robocup_questions.wav"), "--grammar", str(grammar),
                       "--port", str(free_port()), "--workdir", str(tmp_path))
    assert_clear(result, "service asr exited with code 2", "broken.gram")


def test_unknown_alsa_device(tmp_path):
    result = esiaf_run("--mic", "no_such_device_xyz", "--port", str(free_port()), "--workdir", str(tmp_path))
    assert_clear(result, "service grabber exited with code 2", "no_such_device_xyz")


def test_unreachable_orchestrator_is_retried_then_a_clear_error():
    url = f"http://127.0.0.1:{free_port()}"
    result = subprocess.run([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, capture_output=True, text=True,
                            env={**ENV, "ESIAF_ORCHESTRATOR_URL": url, "ESIAF_VAD_REGISTER_TIMEOUT_S": "1.5"},
                            timeout=60)
    assert result.returncode == 2
    assert f"vad: orchestrator at {url} not reachable after 1.5 s" in result.stderr
    assert "attempts" in result.stderr and "Traceback" not in result.stderr


def test_bad_setting_is_one_line():
    result = subprocess.run([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, capture_output=True, text=True,
                            env={**ENV, "ESIAF_VAD_DB_MINN": "3"}, timeout=60)
    assert result.returncode == 2
    assert result.stderr.startswith("vad: unknown setting ESIAF_VAD_DB_MINN")


def test_a_failing_service_does_not_take_others_down(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**ENV, "ESIAF_ORCHESTRATOR_URL": url, "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0",
           "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"}
    procs = [subprocess.Popen([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(port),
                               "--db", str(tmp_path / "o.db")], cwd=REPO, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from esiaf.tools.launcher import OrchestratorClient
        client = OrchestratorClient(url)
        poll(lambda: client.component("vad"), timeout_s=60)
        grabber = subprocess.run([sys.executable, "-m", "esiaf_services.grabber",
                                  "--input", str(tmp_path / "gone.wav")],
                                 cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
        assert grabber.returncode == 2 and "gone.wav does not exist" in grabber.stderr
        assert procs[1].poll() is None and client.component("vad")
        assert httpx.get(f"{url}/health").status_code == 200
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(timeout=10)

"""``python -m esiaf_services.orchestrator`` as a process: clear one-line failures, clean shutdown."""
from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
import zmq

REPO = Path(__file__).resolve().parents[3]
EXIT_TIMEOUT_S = 20.0


def orchestrator_env(**settings: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ESIAF_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    env.update({f"ESIAF_ORCHESTRATOR_{k.upper()}": v for k, v in settings.items()})
    return env


def run_orchestrator(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf_services.orchestrator", *args], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=EXIT_TIMEOUT_S)


def assert_one_clear_line(proc: subprocess.CompletedProcess, *expected: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("orchestrator: ")
    for text in expected:
        assert text in lines[0]


@pytest.fixture
def held_http_port():
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    yield holder.getsockname()[1]
    holder.close()


def test_http_port_in_use_is_one_line_and_exit_2(held_http_port, tmp_path):
    proc = run_orchestrator(["--port", str(held_http_port), "--db", str(tmp_path / "x.db")],
                            orchestrator_env(control_port="0", results_port="0"))
    assert_one_clear_line(
        proc, f"cannot listen on 127.0.0.1:{held_http_port}: address already in use",
        "is another orchestrator running? set --port or ESIAF_ORCHESTRATOR_PORT")


@pytest.mark.parametrize("setting", ["control_port", "results_port"])
def test_zmq_port_in_use_is_one_line_and_exit_2(setting, tmp_path):
    ctx = zmq.Context()
    holder = ctx.socket(zmq.PULL)
    holder.setsockopt(zmq.LINGER, 0)
    port = holder.bind_to_random_port("tcp://127.0.0.1")
    try:
        ports = {"control_port": "0", "results_port": "0", setting: str(port)}
        proc = run_orchestrator(["--port", "0", "--db", str(tmp_path / "x.db")],
                                orchestrator_env(**ports))
    finally:
        ctx.destroy(linger=0)
    assert_one_clear_line(proc, f"tcp://127.0.0.1:{port}: address already in use",
                          f"ESIAF_ORCHESTRATOR_{setting.upper()}")


def test_bad_setting_is_one_line_and_exit_2(tmp_path):
    proc = run_orchestrator(["--db", str(tmp_path / "x.db")], orchestrator_env(contrl_port="1"))
    assert_one_clear_line(proc, "ESIAF_ORCHESTRATOR_CONTRL_PORT")


def test_a_fusion_fusing_its_anchor_type_is_one_line_and_exit_2(tmp_path):
    config = tmp_path / "orchestrator.yaml"
    config.write_text("fusions:\n  - {name: utterance, anchor: speech, fuse: [vad, speech]}\n")
    proc = run_orchestrator(["--config", str(config), "--port", "0", "--db",
                             str(tmp_path / "x.db")],
                            orchestrator_env(control_port="0", results_port="0"))
    assert_one_clear_line(proc, "'utterance'", "anchor type speech cannot also be fused")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_shuts_down_cleanly_with_exit_0(signum, tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "esiaf_services.orchestrator", "--port", "0", "--db",
         str(tmp_path / "x.db"), "--fresh"], cwd=REPO, text=True, stderr=subprocess.PIPE,
        env=orchestrator_env(control_port="0", results_port="0"))
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr],
                              daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + EXIT_TIMEOUT_S
        url = None
        while url is None:
            line = lines.get(timeout=max(deadline - time.monotonic(), 0.01))
            match = re.search(r"event=listening http=(\S+)", line)
            url = match and match.group(1)
        assert httpx.get(f"{url}/health", timeout=5).json() == {"status": "ok"}
        proc.send_signal(signum)
        assert proc.wait(timeout=EXIT_TIMEOUT_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(EXIT_TIMEOUT_S)  # until the end of stderr
    log = []
    while not lines.empty():
        log.append(lines.get())
    assert "Traceback" not in "".join(log), "".join(log)
    assert any("event=orchestrator_stopped" in line for line in log)

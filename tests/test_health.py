"""The containers' healthcheck (python -m esiaf.tools.health) against a real orchestrator and a real service."""
from __future__ import annotations

import os
import subprocess
import sys

from esiaf.tools.health import main as health
from esiaf.tools.testing import REPO, free_port, poll


def test_a_component_is_healthy_while_the_orchestrator_answers_it(orchestrator, tmp_path, capsys):
    health_file = tmp_path / "health"
    assert health(["--file", str(health_file)]) == 1
    assert "missing (not registered" in capsys.readouterr().err
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url,
           "ESIAF_HEALTH_FILE": str(health_file)}
    vad = subprocess.Popen([sys.executable, "-m", "esiaf_services.vad"], cwd=REPO, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        poll(lambda: health_file.exists(), timeout_s=30)
        touched = health_file.stat().st_mtime
        poll(lambda: health_file.stat().st_mtime > touched, timeout_s=3)  # heartbeats keep it fresh
        assert health(["--file", str(health_file), "--max-age", "2"]) == 0
        orchestrator.kill()  # nobody answers any more: unhealthy after max-age
        poll(lambda: health(["--file", str(health_file), "--max-age", "1"]) == 1, timeout_s=5)
        assert "has not answered for" in capsys.readouterr().err
    finally:
        vad.terminate()
        vad.wait(timeout=10)


def test_the_orchestrator_is_healthy_when_its_health_endpoint_answers(orchestrator, capsys):
    assert health(["--url", f"{orchestrator.url}/health"]) == 0
    assert health(["--url", f"http://127.0.0.1:{free_port()}/health"]) == 1
    assert "failed" in capsys.readouterr().err
    assert health(["--url", f"{orchestrator.url}/no-such-page"]) == 1
    assert "answered 404" in capsys.readouterr().err


def test_without_anything_to_check_it_says_so(monkeypatch, capsys):
    monkeypatch.delenv("ESIAF_HEALTH_FILE", raising=False)
    monkeypatch.delenv("ESIAF_SERVICE", raising=False)
    assert health([]) == 1
    assert "no health check" in capsys.readouterr().err

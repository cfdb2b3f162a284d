"""Services on different hosts: each binds and advertises its own address; nothing assumes localhost.

Every service gets its own loopback address here (127.0.0.x), as it would get its own machine.
"""
from __future__ import annotations

import os
import subprocess
import sys

import httpx
import pytest

from esiaf.tools.testing import REPO, free_port, poll, shared_data

pytestmark = pytest.mark.e2e
ORCHESTRATOR_HOST = "127.0.0.4"
HOSTS = {"asr": "127.0.0.2", "vad": "127.0.0.3", "grabber": "127.0.0.5"}


def test_each_service_on_its_own_address(tmp_path):
    raw = shared_data("speech/pocketsphinx/goforward.raw")
    port = free_port()
    url = f"http://{ORCHESTRATOR_HOST}:{port}"
    base = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": url, "ESIAF_STREAM_ID": "hosts"}
    processes = []

    def start(service: str, *args: str, **env: str) -> subprocess.Popen:
        log = (tmp_path / f"{service}.log").open("wb")
        process = subprocess.Popen([sys.executable, "-m", f"esiaf_services.{service}", *args], cwd=REPO,
                                   env={**base, **env}, stdout=log, stderr=subprocess.STDOUT)
        processes.append(process)
        return process

    try:
        start("orchestrator", "--host", ORCHESTRATOR_HOST, "--port", str(port), "--db", str(tmp_path / "o.db"),
              ESIAF_ORCHESTRATOR_CONTROL_PORT="0", ESIAF_ORCHESTRATOR_RESULTS_PORT="0")
        http = httpx.Client(base_url=url, timeout=5)
        poll(lambda: http.get("/health").status_code == 200, timeout_s=30)
        for service in ("asr", "vad"):
            start(service, ESIAF_BIND_HOST=HOSTS[service])
            poll(lambda service=service: any(c["name"] == service for c in http.get("/components").json()["items"]), 60)
        start("grabber", "--input", str(raw), "--fast", ESIAF_BIND_HOST="0.0.0.0",
              ESIAF_ADVERTISE_HOST=HOSTS["grabber"], ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS="1")

        fused = poll(lambda: http.get("/fused", params={"stream": "hosts"}).json()["items"], timeout_s=60)
        assert fused[0]["anchor"]["speech"]["hypotheses"][0]["text"] == "go forward ten meters"
        components = {c["name"]: c for c in http.get("/components", params={"include_dead": "true"}).json()["items"]}
        assert components["vad"]["audio_endpoint"].startswith(f"tcp://{HOSTS['vad']}:")
        # the grabber has played its file and left: the vad connected to the address it advertised
        assert f"connected to producer endpoint=tcp://{HOSTS['grabber']}:" in (tmp_path / "vad.log").read_text()
        assert components["asr"]["audio_endpoint"] is None  # no outputs
    finally:
        for process in reversed(processes):
            process.terminate()
            process.wait(timeout=10)

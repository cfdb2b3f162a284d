"""HTTPS and wss for the orchestrator (optional): with ``tls_cert``/``tls_key`` it serves
TLS only; clients (OrchestratorHTTP, the SDK's registration, the launcher's websocket feed) check
its certificate against ``ESIAF_TLS_CA``. A self-signed certificate is made for each test run."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import httpx
import pytest
import zmq

from esiaf import auth
from esiaf.api_client import OrchestratorHTTP
from esiaf.results import make_result
from esiaf.tools.feed import FusedFeed
from esiaf.tools.testing import REPO, Orchestrator, free_port, poll, signed_result
from tests.test_component import Sink, start

BASE_NS = 1_763_720_000_000_000_000


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to make a certificate with")
    where = tmp_path_factory.mktemp("tls")
    made = subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                           "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost",
                           "-keyout", str(where / "key.pem"), "-out", str(where / "cert.pem")],
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    return where / "cert.pem", where / "key.pem"


@pytest.fixture
def secure(tmp_path, certificate, monkeypatch):
    cert, key = certificate
    monkeypatch.setenv(auth.TLS_CA_ENV, str(cert))  # the self-signed certificate is its own CA
    orchestrator = Orchestrator(tmp_path, {"tls_cert": str(cert), "tls_key": str(key)}, ca=cert)
    yield orchestrator
    orchestrator.close()


def test_the_orchestrator_serves_https_only_and_clients_check_its_certificate(secure):
    assert secure.url.startswith("https://")
    with OrchestratorHTTP(secure.url) as http:  # ESIAF_TLS_CA: the certificate is trusted
        assert http.get("/health").status_code == 200
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(f"{secure.url}/health", timeout=5)  # the system's CAs do not know it
    with pytest.raises(httpx.HTTPError):
        httpx.get(f"http://127.0.0.1:{secure.port}/health", timeout=5)  # no plain HTTP beside it
    assert "event=listening http=https://" in (secure.db_path.parent / "orchestrator.log").read_text()


def test_components_register_over_https_and_the_feed_follows_over_wss(secure):
    sink, thread = start(Sink, secure.url)  # the SDK's registration and heartbeats
    try:
        poll(lambda: secure.component("sink"), timeout_s=20)
        registration = secure.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
        with FusedFeed(f"{secure.ws_url}/ws/fused") as feed:
            context = zmq.Context()
            try:
                push = context.socket(zmq.PUSH)
                push.setsockopt(zmq.LINGER, 0)
                push.connect(registration["results_endpoint"])
                push.send_multipart(signed_result(registration, make_result(
                    "asr", "speech", "s", (BASE_NS, BASE_NS + 10**9), 1,
                    speech={"hypotheses": [{"text": "over tls", "probability": 1.0}]})))
                fused = json.loads(feed.recv(timeout=10))
            finally:
                context.destroy(linger=0)
        assert fused["type"] == "fused_result" and fused["anchor"]["speech"]["hypotheses"][0]["text"] == "over tls"
    finally:
        sink.stop()
        thread.join(10)


def test_a_certificate_that_cannot_be_used_is_one_line_and_exit_2(tmp_path, certificate):
    cert, _ = certificate
    done = subprocess.run([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(free_port()),
                           "--db", str(tmp_path / "o.db")], cwd=REPO, capture_output=True, text=True, timeout=60,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO),
                               "ESIAF_ORCHESTRATOR_TLS_CERT": str(cert),
                               "ESIAF_ORCHESTRATOR_TLS_KEY": str(tmp_path / "missing.pem")})
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("orchestrator: cannot use the TLS certificate")

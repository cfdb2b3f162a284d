"""A peer without the token holding half-sent HTTP requests cannot take the orchestrator down
(esiaf_services/orchestrator/connections.py): the orchestrator as a process with the file limit many
Linux services get (1024), the peer on another loopback address."""
from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import websockets.sync.client

from esiaf.tools.testing import REPO, Orchestrator, free_port, half_sent_requests, poll

TOKEN = "half-open-token"
REQUEST_TIMEOUT_S = 2.0
PER_PEER = 256


def still_open(sock: socket.socket) -> bool:
    """Whether the server still holds this connection: it has neither closed it nor answered on it."""
    sock.setblocking(False)
    try:
        sock.recv(1, socket.MSG_PEEK)
    except BlockingIOError:
        return True
    except OSError:
        pass
    return False


def health(port: int) -> int:
    """``GET /health`` on a new connection, as a health check asks it: the status, 0 if none in 5 s."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: esiaf\r\nConnection: close\r\n\r\n")
            return int(sock.recv(64).split(b" ")[1])
    except (OSError, IndexError, ValueError):
        return 0


@pytest.fixture
def orchestrator(tmp_path):
    orchestrator = Orchestrator(tmp_path, config={"request_timeout_s": REQUEST_TIMEOUT_S},
                                env={"ESIAF_TOKEN": TOKEN}, open_files=1024)
    yield orchestrator
    orchestrator.close()


def test_1100_half_sent_requests_neither_stop_health_nor_fill_the_log(orchestrator, tmp_path):
    log = tmp_path / "orchestrator.log"
    log_before = log.stat().st_size
    held = half_sent_requests("127.0.0.1", orchestrator.port, 1100)
    try:
        assert len(held) > 1000  # the kernel took them: the orchestrator has to deal with each
        statuses = [health(orchestrator.port) for _ in range(20)]
        assert statuses == [200] * 20
        # at most its bound of the peer's connections is held; the others were closed as they came
        assert sum(still_open(sock) for sock in held) <= PER_PEER
        # and those it holds are closed once their request has not come whole in time, with a 408
        poll(lambda: not any(still_open(sock) for sock in held), timeout_s=REQUEST_TIMEOUT_S + 10)
        answers = [sock.recv(64) for sock in held if _readable(sock)]
        assert sum(answer.startswith(b"HTTP/1.1 408") for answer in answers) >= 1
        assert health(orchestrator.port) == 200
        metrics = orchestrator.http.get("/metrics", headers={"Authorization": f"Bearer {TOKEN}"}).text
        assert refused_http(metrics, "peer_limit") >= len(held) - PER_PEER
        assert refused_http(metrics, "request_timeout") >= 1
    finally:
        for sock in held:
            sock.close()
    text = log.read_bytes()[log_before:]
    assert len(text) < 1_000_000 and b"Traceback" not in text
    assert b"event=http_connection_refused reason=peer_limit" in text
    assert b"event=http_connection_refused reason=request_timeout" in text


def refused_http(metrics_text: str, reason: str) -> float:
    from prometheus_client.parser import text_string_to_metric_families
    return sum(sample.value for family in text_string_to_metric_families(metrics_text) for sample in family.samples
               if sample.name == "esiaf_refused_http_connections_total" and sample.labels["reason"] == reason)


def _readable(sock: socket.socket) -> bool:
    sock.setblocking(False)
    try:
        return bool(sock.recv(1, socket.MSG_PEEK))
    except OSError:
        return False


def test_a_trickled_request_is_cut_at_its_deadline_but_a_long_poll_and_a_websocket_are_not(orchestrator):
    headers = {"Authorization": f"Bearer {TOKEN}"}
    with websockets.sync.client.connect(f"{orchestrator.ws_url}/ws/fused?token={TOKEN}") as ws, \
            socket.create_connection(("127.0.0.1", orchestrator.port), timeout=REQUEST_TIMEOUT_S * 5) as slow:
        etag = orchestrator.http.get("/voices", params={"embeddings": 1}, headers=headers).headers["etag"]
        slow.sendall(b"POST /voices/x HTTP/1.1\r\nHost: esiaf\r\nAuthorization: Bearer %s\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"st" % TOKEN.encode())
        # a long poll outlasting the request deadline: the request came whole, its answer may take long
        answer = orchestrator.http.get("/voices", params={"embeddings": 1, "wait_s": REQUEST_TIMEOUT_S * 1.5},
                                       headers={**headers, "If-None-Match": etag}, timeout=REQUEST_TIMEOUT_S * 5)
        assert answer.status_code == 304
        # meanwhile the body that never came whole was cut, and the websocket is still served
        assert slow.recv(64) == b""
        assert ws.ping().wait(5)


def test_the_file_limit_is_raised_to_the_hard_limit_at_start_up(tmp_path):
    port = free_port()

    def soft_1024_hard_4096() -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 4096))

    process = subprocess.Popen([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(port),
                                "--db", str(tmp_path / "o.db")], cwd=REPO, preexec_fn=soft_1024_hard_4096,
                               env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO),
                                    "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0", "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"},
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        poll(lambda: httpx.get(f"http://127.0.0.1:{port}/health").status_code == 200, timeout_s=90)
        limits = Path(f"/proc/{process.pid}/limits").read_text()
        line = next(line for line in limits.splitlines() if line.startswith("Max open files"))
        assert line.split()[3:5] == ["4096", "4096"]
    finally:
        process.terminate()
        process.wait(timeout=10)


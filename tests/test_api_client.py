"""The one client of the orchestrator's API (esiaf/api_client.py): what it retries and for how long,
against a real HTTP server that answers as scripted."""
from __future__ import annotations

import http.server
import threading
import time

import httpx
import pytest

from esiaf.api_client import OrchestratorHTTP
from esiaf.control import RegistrationError, register
from esiaf.tools.testing import free_port


class Scripted:
    """A real HTTP server on loopback whose answers are (status, headers) popped in order (the last repeats)."""

    def __init__(self, answers: list[tuple[int, dict[str, str]]], port: int = 0, body: bytes = b"") -> None:
        self.answers, self.requests = list(answers), []
        scripted = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def _answer(self) -> None:
                scripted.requests.append((self.command, self.path, self.headers.get("Authorization")))
                status, headers = scripted.answers.pop(0) if len(scripted.answers) > 1 else scripted.answers[0]
                content = body or b'{"detail": "scripted"}'
                self.send_response(status)
                for name, value in {**headers, "Content-Type": "application/json",
                                    "Content-Length": str(len(content))}.items():
                    self.send_header(name, value)
                self.end_headers()
                self.wfile.write(content)

            do_GET = do_POST = do_PUT = do_DELETE = _answer

            def log_message(self, *args) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def scripted():
    servers = []

    def make(*answers):
        servers.append(Scripted(list(answers)))
        return servers[-1]
    yield make
    for server in servers:
        server.close()


def test_5xx_and_409_with_retry_after_are_tried_again_a_refusal_is_not(scripted, monkeypatch):
    monkeypatch.setenv("ESIAF_TOKEN", "t0ken")
    server = scripted((503, {}), (409, {"Retry-After": "1"}), (201, {}))
    with OrchestratorHTTP(server.url) as http:
        why = []
        assert http.request("POST", "/components", retry_for_s=10, on_retry=why.append).status_code == 201
        assert http.attempts == 3 and why == ["HTTP 503: scripted", "scripted"]
    assert [r[2] for r in server.requests] == ["Bearer t0ken"] * 3  # the token on every attempt
    refused = scripted((422, {}))
    with OrchestratorHTTP(refused.url) as http:
        assert http.request("POST", "/components", retry_for_s=10).status_code == 422 and http.attempts == 1
    conflict = scripted((409, {}))  # a conflict that waiting will not end (no Retry-After)
    with OrchestratorHTTP(conflict.url) as http:
        assert http.request("POST", "/components", retry_for_s=10).status_code == 409 and http.attempts == 1


def test_an_unreachable_orchestrator_is_tried_until_the_time_allowed_then_the_error_is_raised():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens
    with OrchestratorHTTP(url) as http:
        started = time.monotonic()
        with pytest.raises(httpx.ConnectError):
            http.request("GET", "/health", retry_for_s=1.0)
        took = time.monotonic() - started
        assert 0.5 < took < 1.5 and http.attempts >= 4  # waits of 0.1, 0.2, 0.4, ... within the second
        with pytest.raises(httpx.ConnectError):
            http.request("GET", "/health", retry_for_s=30, stopping=lambda: True)
        assert http.attempts == 1  # shutting down: no second attempt


REGISTERED = (b'{"component_id": "x-1", "control_endpoint": "tcp://127.0.0.1:1", "results_endpoint": '
              b'"tcp://127.0.0.1:2", "heartbeat_interval_s": 0.5, "dead_after_s": 2.5}')


def test_registration_waits_for_an_orchestrator_that_comes_up_and_says_why_it_gave_up(scripted):
    with pytest.raises(RegistrationError, match=r"not reachable after 0.3 s \(\d+ attempts\): "):
        register(f"http://127.0.0.1:{free_port()}", {"name": "x"}, timeout_s=0.3)  # nothing listens
    port, late = free_port(), []
    # the orchestrator comes up 0.6 s after the component started registering
    threading.Timer(0.6, lambda: late.append(Scripted([(201, {})], port=port, body=REGISTERED))).start()
    try:
        started = time.monotonic()
        registration = register(f"http://127.0.0.1:{port}", {"name": "x"}, timeout_s=10)
        assert registration.component_id == "x-1" and 0.5 < time.monotonic() - started < 3
    finally:
        for server in late:
            server.close()
    refusing = scripted((422, {}))
    with pytest.raises(RegistrationError, match=r"refused registration \(422\): scripted") as refused:
        register(refusing.url, {"name": "x"}, timeout_s=5)
    assert refused.value.refused

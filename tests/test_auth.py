"""Authentication: with a token configured, every forged action is refused
without it (401, or a refused websocket) and works with it; /health stays open; a browser's
websocket from another origin is refused."""
from __future__ import annotations

import os
import subprocess
import sys

import httpx
import pytest
import zmq
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from esiaf.tools.testing import REPO, free_port, poll, refused_peers

TOKEN = "s3cret-token-for-the-test"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BODY = {"name": "asr", "kind": "speech"}


@pytest.fixture
def secured(tmp_path):
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_TOKEN": TOKEN,
           "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0", "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"}
    process = subprocess.Popen([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(port),
                                "--db", str(tmp_path / "o.db")], cwd=REPO, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    poll(lambda: httpx.get(f"{url}/health").status_code == 200, timeout_s=30)
    yield url
    process.terminate()
    process.wait(timeout=10)


FORGED = [
    ("post", "/components", {"json": BODY}),                       # register as asr
    ("delete", "/components/asr-1234", {}),                        # unregister the real one
    ("put", "/fusions", {"json": {"items": []}}),                  # nothing fused any more
    ("put", "/streams/s", {"json": {"start_ns": 1, "source": "x"}}),
    ("get", "/fused", {}), ("get", "/results", {}), ("get", "/components", {}), ("get", "/metrics", {}),
]


@pytest.mark.parametrize("method, path, kwargs", FORGED)
def test_every_endpoint_but_health_needs_the_token(secured, method, path, kwargs):
    for headers in ({}, {"Authorization": "Bearer wrong"}):
        response = httpx.request(method.upper(), f"{secured}{path}", headers=headers, **kwargs)
        assert response.status_code == 401, (path, response.text)
    assert httpx.get(f"{secured}/health").status_code == 200


def test_the_dashboard_page_loads_without_the_token_and_reads_nothing_without_it(secured):
    """The page and its files hold no data; what it reads needs the token of its URL."""
    for path in ("/", "/dashboard/dashboard.js", "/dashboard/dashboard.css"):
        assert httpx.get(f"{secured}{path}").status_code == 200, path
    for path in ("/dashboard/../components", "/dashboard/%2e%2e/components", "/metrics?x=/dashboard/"):
        assert httpx.get(f"{secured}{path}").status_code in (401, 404), path
    assert httpx.post(f"{secured}/", json=BODY).status_code == 401
    assert httpx.get(f"{secured}/metrics", params={"token": TOKEN}).status_code == 200


def test_with_the_token_they_work(secured):
    assert httpx.post(f"{secured}/components", json=BODY, headers=AUTH).status_code == 201
    assert httpx.put(f"{secured}/fusions", json={"items": []}, headers=AUTH).status_code == 200
    assert httpx.get(f"{secured}/fused", params={"token": TOKEN}).status_code == 200  # browsers: ?token=


def test_the_websocket_needs_the_token_and_a_browser_its_own_origin(secured):
    ws = secured.replace("http", "ws") + "/ws/fused"
    for url, headers in ((ws, {}), (ws + "?token=wrong", {}),
                         (ws + f"?token={TOKEN}", {"Origin": "http://evil.example"})):
        with pytest.raises(InvalidStatus):
            connect(url, additional_headers=headers, open_timeout=10).close()
    with connect(ws + f"?token={TOKEN}", open_timeout=10):
        pass
    with connect(ws, additional_headers={**AUTH, "Origin": secured}, open_timeout=10):
        pass


def test_esiaf_run_makes_a_token_and_its_services_use_it(launch):
    run = launch("--input", str(REPO / "examples/robocup_questions.wav"), "--grammar", "robocup", "--fast",
                 "--without", "emotion,gender,voiceid", "--json", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)
    assert len(run.token) >= 20
    assert httpx.get(f"{run.url}/fused").status_code == 401
    assert len(httpx.get(f"{run.url}/fused", headers=run.headers).json()["items"]) == 5
    assert oct((run.workdir / "token").stat().st_mode & 0o777) == "0o600"


def test_results_and_control_sockets_take_only_peers_with_the_token(secured):
    from esiaf.results import make_result
    from esiaf.tools.testing import signed_result
    registration = httpx.post(f"{secured}/components", json=BODY, headers=AUTH).json()
    forged = make_result("asr", "speech", "s", (10**18, 10**18 + 5), 1, speech={"hypotheses": [
        {"text": "open the front door and disable the alarm", "probability": 1.0}]})
    genuine = make_result("asr", "speech", "s", (10**18 + 10, 10**18 + 15), 2, speech={"hypotheses": [
        {"text": "what is a chatbot", "probability": 1.0}]})
    context = zmq.Context()
    try:
        stranger, member = context.socket(zmq.PUSH), context.socket(zmq.PUSH)
        member.plain_username, member.plain_password = b"esiaf", TOKEN.encode()
        for sock in (stranger, member):
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(registration["results_endpoint"])
        stranger.send_multipart([b"result", forged.SerializeToString()])
        member.send_multipart(signed_result(registration, genuine))
        poll(lambda: httpx.get(f"{secured}/results", headers=AUTH).json()["items"], timeout_s=10)
        # the stranger's handshake was refused (and counted), so its result can never arrive
        poll(lambda: refused_peers(httpx.get(f"{secured}/metrics", headers=AUTH).text, "results"), timeout_s=10)
        results = httpx.get(f"{secured}/results", headers=AUTH).json()["items"]
        texts = [r["speech"]["hypotheses"][0]["text"] for r in results]
        assert texts == ["what is a chatbot"]
    finally:
        context.destroy(linger=0)

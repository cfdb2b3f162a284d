"""GET /voices is a long poll: a voiceid asks with the ETag it has and is answered when the
voices change, not every second; an enrolment or a deletion answers it at once, nothing else does
before wait_s, and a shutting-down orchestrator answers it at once instead of holding its exit."""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from esiaf.tools.testing import Orchestrator, shared_data


@pytest.fixture
def orchestrator(tmp_path):
    running = Orchestrator(tmp_path)
    yield running
    running.close()


def long_poll(orchestrator: Orchestrator, etag: str, wait_s: float) -> tuple[httpx.Response, float]:
    started = time.monotonic()
    with httpx.Client(base_url=orchestrator.url, timeout=wait_s + 10) as client:
        reply = client.get("/voices", params={"embeddings": 1, "wait_s": wait_s}, headers={"If-None-Match": etag})
    return reply, time.monotonic() - started


def enrol(orchestrator: Orchestrator, name: str) -> None:
    wav = shared_data("speech/cmu_arctic/cmu_arctic_us_aew_a0001.wav").read_bytes()
    reply = orchestrator.http.post(f"/voices/{name}", files={"audio": ("a.wav", wav)}, timeout=60)
    assert reply.status_code == 200, reply.text


def test_a_long_poll_is_answered_by_a_change_at_once_and_otherwise_after_wait_s(orchestrator):
    enrol(orchestrator, "Anna")  # the encoder is loaded: the timings below are not its loading
    etag = orchestrator.http.get("/voices", params={"embeddings": 1}).headers["ETag"]
    unchanged, waited = long_poll(orchestrator, etag, 1.0)
    assert unchanged.status_code == 304 and unchanged.headers["ETag"] == etag
    assert 0.9 <= waited < 5
    stale, waited = long_poll(orchestrator, '"0-0"', 20)  # another ETag: answered at once
    assert stale.status_code == 200 and waited < 3
    assert [v["name"] for v in stale.json()["voices"]] == ["Anna"]
    with ThreadPoolExecutor() as pool:
        waiting = pool.submit(long_poll, orchestrator, etag, 30)
        time.sleep(1.0)
        assert not waiting.done()
        changed_at = time.monotonic()
        enrol(orchestrator, "Ben")
        reply, _ = waiting.result(timeout=20)
        assert time.monotonic() - changed_at < 5  # not the 30 s of wait_s
    assert reply.status_code == 200 and reply.headers["ETag"] != etag
    assert sorted(v["name"] for v in reply.json()["voices"]) == ["Anna", "Ben"]
    with ThreadPoolExecutor() as pool:
        waiting = pool.submit(long_poll, orchestrator, reply.headers["ETag"], 30)
        time.sleep(1.0)
        assert orchestrator.http.delete("/voices/Ben").status_code == 200
        deleted, waited = waiting.result(timeout=20)
    assert deleted.status_code == 200 and waited < 10
    assert [v["name"] for v in deleted.json()["voices"]] == ["Anna"]


def test_a_long_poll_does_not_hold_the_orchestrator_at_shutdown(orchestrator):
    etag = orchestrator.http.get("/voices", params={"embeddings": 1}).headers["ETag"]
    with ThreadPoolExecutor() as pool:
        waiting = pool.submit(long_poll, orchestrator, etag, 30)
        time.sleep(1.0)
        stopped_at = time.monotonic()
        orchestrator.process.terminate()
        assert orchestrator.process.wait(timeout=20) == 0
        assert time.monotonic() - stopped_at < 2.5  # uvicorn would wait up to 3 s for the request
        reply, _ = waiting.result(timeout=10)
    assert reply.status_code == 304


def test_wait_s_is_bounded(orchestrator):
    for bad in ("-1", "61", "soon"):
        reply = orchestrator.http.get("/voices", params={"embeddings": 1, "wait_s": bad})
        assert reply.status_code == 422, bad

"""schemathesis against the orchestrator's OpenAPI document: a real orchestrator
process with a token, every operation of its /openapi.json, every check (``--checks all``: server
errors, status codes, content types, headers and bodies the document does not declare, bad input
taken, good input refused, auth ignored, wrong ``Allow`` headers, ...) in every phase (the
document's examples, coverage of its boundaries, fuzzing, stateful sequences). A fixed seed and a
bounded number of examples keep it reproducible and under a minute on two cores.

What is not fuzzed, and why, is in schemathesis.toml beside this file; the websocket /ws/fused is
not in the OpenAPI document at all (tests/test_auth.py and test_orchestrator_results.py cover it).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from esiaf.tools.testing import Orchestrator

SEED = 20261123
MAX_EXAMPLES = 30  # per operation, in the fuzzing phase (the other phases add theirs)
TOKEN = "fuzz-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CONFIG = Path(__file__).with_name("schemathesis.toml")
TIMEOUT_S = 300


@pytest.fixture
def orchestrator(tmp_path):
    running = Orchestrator(tmp_path, config={"token": TOKEN})
    yield running
    running.close()


def test_the_api_does_what_its_openapi_says(orchestrator, tmp_path):
    report = tmp_path / "schemathesis.json"
    run = subprocess.run(
        [sys.executable, "-m", "schemathesis.cli", "--config-file", str(CONFIG), "run",
         f"{orchestrator.url}/openapi.json", "--header", f"Authorization: Bearer {TOKEN}",
         "--checks", "all", "--seed", str(SEED), "--max-examples", str(MAX_EXAMPLES), "--workers", "1",
         "--report", "json", "--report-json-path", str(report), "--output-sanitize", "false"],
        cwd=tmp_path, capture_output=True, text=True, timeout=TIMEOUT_S)  # its caches go there too
    assert run.returncode == 0, run.stdout[-20000:] + run.stderr[-2000:]
    outcome = json.loads(report.read_text())
    operations, cases = outcome["operations"], outcome["test_cases"]
    print(f"\nschemathesis: {operations['tested']} of {operations['total']} operations, "
          f"{cases['generated']} test cases, {cases['unique_failures']} failures")
    assert operations["tested"] == operations["total"] - 2  # all but POST /voices/{name}, /streams/{s}/play
    assert not outcome["failures"] and not outcome["errors"] and cases["generated"] > 500


@pytest.mark.parametrize("method, path, body", [
    ("GET", "/results?after_id=99999999999999999999", None),
    ("GET", "/results?end_ns=99999999999999999999", None),
    ("GET", "/fused?start_ns=-99999999999999999999", None),
    ("PUT", "/streams/s", {"start_ns": 99999999999999999999}),
    ("POST", "/voices/bob", {"stream": "s", "start_ns": 0, "end_ns": 99999999999999999999}),
])
def test_numbers_past_sqlites_integers_are_422_not_500(orchestrator, method, path, body):
    response = httpx.request(method, orchestrator.url + path, json=body, headers=AUTH, timeout=10)
    assert response.status_code == 422, response.text


def test_405_names_every_method_of_the_path(orchestrator):
    response = httpx.request("PATCH", f"{orchestrator.url}/components", headers=AUTH, timeout=10)
    assert response.status_code == 405 and response.headers["allow"] == "GET, POST"

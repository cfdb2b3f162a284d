"""What the container tests share: running commands, a compose project of their own, the
example's truth and a websocket collector (the fixtures that build the images and make projects
are in tests/conftest.py)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import uuid
from pathlib import Path

import httpx
import pytest
from websockets.sync.client import connect

from esiaf.tools.testing import REPO, free_port

EXAMPLE = REPO / "examples" / "robocup_questions.wav"
TRUTH = [s["text"] for s in json.loads((REPO / "examples" / "robocup_questions.json").read_text())["sentences"]]
BUILD_TIMEOUT_S = 45 * 60


def run(*cmd: str, timeout: float = 300, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {result.returncode}:\n"
                             f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


def compose_command() -> list[str] | None:
    if shutil.which("docker") and run("docker", "compose", "version", check=False).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None



def input_folder(folder: Path, wav: Path) -> Path:
    """The grabber's mounted folder, holding ``wav`` as speech.wav, readable by the containers' user."""
    folder.mkdir(parents=True)
    shutil.copy(wav, folder / "speech.wav")
    folder.chmod(0o755)
    (folder / "speech.wav").chmod(0o644)
    return folder


def at_least(count: int, items: list) -> list | None:
    return items if len(items) >= count else None


def best_text(fused: dict) -> str:
    """The recognised text ('' for an utterance fused without its dead recogniser: anchored on its VAD segment)."""
    hypotheses = fused["anchor"].get("speech", {}).get("hypotheses")
    return hypotheses[0]["text"] if hypotheses else ""


class Project:
    """One compose project of our own (its own name, port and input folder), downed at the end."""

    def __init__(self, tmp_path: Path, wav: Path):
        compose = compose_command()
        if compose is None:
            pytest.skip("neither `docker compose` nor `docker-compose` is installed")
        self.name = f"esiaftest{uuid.uuid4().hex[:8]}"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        inputs = tmp_path / "input"
        input_folder(inputs, wav)
        self.env = {**os.environ, "ESIAF_HTTP_PORT": str(self.port), "ESIAF_INPUT_DIR": str(inputs),
                    "ESIAF_INPUT_FILE": "speech.wav", "ESIAF_STREAM_ID": self.name}
        self.compose = [*compose, "-p", self.name]  # compose.yaml and compose.override.yaml, from REPO
        self.http = httpx.Client(base_url=self.url, timeout=5)

    def __call__(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess:
        return run(*self.compose, *args, timeout=timeout, check=check, env=self.env, cwd=REPO)

    def leftovers(self) -> dict[str, list[str]]:
        label = f"label=com.docker.compose.project={self.name}"
        found = {kind: run("docker", kind, "ls", *(["-a"] if kind == "container" else []), "-q",
                           "--filter", label).stdout.split() for kind in ("container", "network", "volume")}
        return {kind: ids for kind, ids in found.items() if ids}

    def fused(self, fusion: str = "speech") -> list[dict]:
        params = {"stream": self.name, "fusion": fusion, "limit": 100}
        return self.http.get("/fused", params=params).json()["items"]

    def components(self) -> dict[str, dict]:
        items = self.http.get("/components", params={"include_dead": "true"}).json()["items"]
        return {c["component_id"]: c for c in items}

    def logs(self) -> str:
        return self("logs", "--no-color", "--tail", "60", check=False).stdout


def websocket_collector(url: str, stream: str, into: list, stop: threading.Event) -> threading.Thread:
    """Collects fused results from the websocket, as a client on the host would, until stopped."""
    def collect():
        ws_url = url.replace("http", "ws") + f"/ws/fused?stream={stream}&after_id=0"
        with connect(ws_url, open_timeout=30) as ws:
            while not stop.is_set():
                try:
                    message = json.loads(ws.recv(timeout=0.5))
                except TimeoutError:
                    continue
                into.append(message)
    thread = threading.Thread(target=collect, daemon=True)
    thread.start()
    return thread


def http_status(http: httpx.Client, path: str) -> int:
    try:
        return http.get(path).status_code
    except httpx.HTTPError:
        return 0


def subscribers(http: httpx.Client, topic: str) -> int:
    """Subscribers of a topic's producers, as they report them (the asr connected to the vad)."""
    for item in http.get("/topics").json()["items"]:
        if item["topic"] == topic:
            return sum(p["subscribers"] or 0 for p in item["producers"])
    return 0

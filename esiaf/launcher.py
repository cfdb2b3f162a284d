"""Runs ESIAF services as plain child processes and supervises them.

Each service runs as ``python -m services.<name>`` with its log in
``<workdir>/logs/<name>.log``. A child that dies on its own is reported with
the tail of its log. Stopping sends SIGTERM to every child (newest first),
waits, then SIGKILLs what is left; children also get SIGTERM if the launcher
itself dies (PR_SET_PDEATHSIG), so no process is left orphaned.
"""
from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import httpx

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
_PR_SET_PDEATHSIG = 1


class LaunchError(Exception):
    """A service did not come up; the message says which and why."""


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path

    def tail(self, lines: int = 12) -> str:
        try:
            text = self.log_path.read_text(errors="replace").rstrip().splitlines()
        except OSError:
            return ""
        return "\n".join(f"    {line}" for line in text[-lines:])


@dataclass
class Supervisor:
    workdir: Path
    env: dict[str, str] = field(default_factory=dict)
    children: list[Child] = field(default_factory=list)

    def start(self, name: str, args: list[str] = (), env: dict[str, str] | None = None) -> Child:
        logs = self.workdir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        log_path = logs / f"{name}.log"
        child_env = {**os.environ, **self.env, **(env or {})}
        child_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), child_env.get("PYTHONPATH")]))
        with log_path.open("wb") as out:
            process = subprocess.Popen([sys.executable, "-m", f"services.{name}", *args], stdout=out,
                                       stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=child_env,
                                       cwd=REPO_ROOT, start_new_session=True, preexec_fn=_die_with_parent)
        child = Child(name, process, log_path)
        self.children.append(child)
        log.info("started service=%s pid=%d log=%s", name, process.pid, log_path)
        return child

    def exited(self) -> list[Child]:
        return [c for c in self.children if c.process.poll() is not None]

    def failure(self, child: Child) -> str:
        return (f"service {child.name} exited with code {child.process.returncode}; "
                f"its log ({child.log_path}) ends:\n{child.tail()}")

    def stop(self, timeout_s: float = 5.0) -> None:
        for child in reversed(self.children):
            if child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for child in reversed(self.children):
            try:
                child.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("service=%s did not stop in %g s: killing it", child.name, timeout_s)
                child.process.kill()
                child.process.wait()


def wait_until(condition: Callable[[], Any], supervisor: Supervisor, what: str, timeout_s: float,
               watch: Child | None = None) -> Any:
    """Polls ``condition`` until it returns something truthy; fails if a child dies or time runs out."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = condition()
        except httpx.HTTPError:
            value = None
        if value:
            return value
        for child in supervisor.exited():
            if child is watch or child.process.returncode != 0:
                raise LaunchError(supervisor.failure(child))
        if time.monotonic() > deadline:
            extra = f"; its log ({watch.log_path}) ends:\n{watch.tail()}" if watch else ""
            raise LaunchError(f"timed out after {timeout_s:g} s waiting for {what}{extra}")
        time.sleep(0.05)


class OrchestratorClient:
    def __init__(self, url: str):
        self.url = url.rstrip("/")
        self._http = httpx.Client(timeout=2.0)

    def healthy(self) -> bool:
        return self._http.get(f"{self.url}/health").status_code == 200

    def components(self) -> list[dict[str, Any]]:
        response = self._http.get(f"{self.url}/components")
        response.raise_for_status()
        return response.json()["items"]

    def component(self, name: str) -> dict[str, Any] | None:
        return next((c for c in self.components() if c.get("name") == name), None)

    def topics(self) -> list[dict[str, Any]]:
        response = self._http.get(f"{self.url}/topics")
        response.raise_for_status()
        return response.json()["items"]

    def stream(self, stream_id: str) -> dict[str, Any] | None:
        response = self._http.get(f"{self.url}/streams/{stream_id}")
        if response.status_code == 404:
            return None
        response.raise_for_status()
        return response.json()

    def close(self) -> None:
        self._http.close()

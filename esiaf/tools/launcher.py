"""Runs ESIAF services as plain child processes and supervises them.

Each service runs as ``python -m esiaf_services.<name>`` with its log in
``<workdir>/logs/<name>.log``. A child that dies on its own is reported with
the tail of its log. Stopping sends SIGTERM to every child (newest first),
waits, then SIGKILLs what is left; children also get SIGTERM if the launcher
itself dies (PR_SET_PDEATHSIG), so no process is left orphaned.
"""
from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any
from urllib.parse import quote

import httpx

from esiaf.api_client import OrchestratorHTTP
from esiaf.settings import STANDBY_ENV
from esiaf.tools.errors import LaunchError
from esiaf.tools.terminal import err

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
_PR_SET_PDEATHSIG = 1
MAX_RESTARTS = 5  # a service that died this often in a row is not restarted again: the run ends
STABLE_AFTER_S = 60.0  # a service that ran this long before dying was not crash-looping: its count starts again
RESTART_BACKOFF_S = 0.5  # before the first restart; doubles with each, up to 10 s
MAX_LOG_READ = 1 << 20  # a child's log read for refusals at most this much at a time
REFUSAL = " refused "  # a service's log line that says it refused something (esiaf/receiving.py)
START_TIMEOUT_S = 60.0  # esiaf run: how long a service may take to answer, register, subscribe or start playing
# a service that keeps a spare (the vad: every analyser hears speech through it) gets one once the pipeline
# is up (Supervisor.ready: every service registered and subscribed, so the spare's start does not slow the
# pipeline's own), or this long after its current process started (after a restart; or where nothing says
# the pipeline is up)
SPARE_AFTER_S = 10.0


def _die_with_parent() -> None:
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path
    command: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    restarts: int = 0
    died_at: float | None = None  # monotonic time its death was first seen
    started_at: float = field(default_factory=time.monotonic)  # of its current process
    reported: bool = False  # its death was reported to the orchestrator
    log_read: int = 0  # how far its log has been read for refusals
    keeps_spare: bool = False  # a spare process waits, imported, to take over when it dies
    spare: subprocess.Popen | None = None

    def new_refusals(self) -> list[str]:
        """The lines its log has gained since the last call that say it refused something (what it
        logs itself: the first of a reason and every 100th), without their time stamp; at most
        MAX_LOG_READ bytes a call."""
        try:
            with self.log_path.open("rb") as log_file:
                log_file.seek(self.log_read)
                data = log_file.read(MAX_LOG_READ)
        except OSError:
            return []
        end = data.rfind(b"\n") + 1  # whole lines only; the rest is read once it is whole
        if end == 0 and len(data) == MAX_LOG_READ:
            end = len(data)
        self.log_read += end
        lines = data[:end].decode(errors="replace").splitlines()
        return [line.split("] ", 1)[-1] for line in lines if REFUSAL in line]

    def restart_delay_s(self) -> float:
        return min(RESTART_BACKOFF_S * 2 ** self.restarts, 10.0)

    def how_it_ended(self) -> str:
        code = self.process.returncode
        if code is not None and code < 0:
            try:
                return f"killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"killed by signal {-code}"
        return f"exited with code {code}"

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
    up: bool = False  # every service registered and subscribed (ready()): first spares need not wait

    def ready(self) -> None:
        """The pipeline is up: each service that keeps a spare gets its first one now (keep_spares)."""
        self.up = True
        self.keep_spares()

    def start(self, name: str, args: Sequence[str] = (), env: dict[str, str] | None = None,
              target: list[str] | None = None, instance: str | None = None, spare: bool = False) -> Child:
        """Starts ``python -m esiaf_services.<name>`` (or ``python <target...>``, a plug-in) with ``args``;
        ``instance``: one of several instances of the service, under this id (its child and log name);
        ``spare``: keep a spare of it (:meth:`keep_spares`), which takes over when it dies."""
        logs = self.workdir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        logs.chmod(0o700)  # its logs are its owner's (open_log)
        log_path = logs / f"{instance or name}.log"
        child_env = {**os.environ, **self.env, **(env or {})}
        if instance:  # the common setting: a plug-in's service may not be named as its folder
            child_env["ESIAF_INSTANCE"] = instance
        child_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), child_env.get("PYTHONPATH")]))
        command = [sys.executable, *(target or ["-m", f"esiaf_services.{name}"]), *args]
        child = Child(instance or name, self._spawn(command, child_env, log_path, "wb"), log_path, command, child_env,
                      keeps_spare=spare)
        self.children.append(child)
        log.info("started service=%s pid=%d log=%s", child.name, child.process.pid, log_path)
        return child

    @staticmethod
    def _spawn(command: list[str], env: dict[str, str], log_path: Path, mode: str,
               standby: bool = False) -> subprocess.Popen:
        with open_log(log_path, mode) as out:
            return subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.PIPE if standby else subprocess.DEVNULL,
                                    env={**env, STANDBY_ENV: "1"} if standby else env, cwd=REPO_ROOT,
                                    start_new_session=True, preexec_fn=_die_with_parent)

    def keep_spares(self) -> None:
        """Starts a spare of each child that keeps one and has none, once the pipeline is up (a child
        never restarted) or SPARE_AFTER_S after its current process started: the same command, imported
        and waiting (esiaf/runner.py, ESIAF_STANDBY), so a restart costs a registration instead of a whole
        start (the imports alone take seconds on a busy robot). A spare that died is started again the
        same way."""
        now = time.monotonic()
        for child in self.children:
            if child.spare is not None and child.spare.poll() is not None:
                log.warning("the spare of service=%s ended with code %s", child.name, child.spare.returncode)
                child.spare = None
            if (child.keeps_spare and child.spare is None and child.process.poll() is None
                    and ((self.up and not child.restarts) or now - child.started_at >= SPARE_AFTER_S)):
                child.spare = self._spawn(child.command, child.env, child.log_path, "ab", standby=True)
                log.info("spare of service=%s started pid=%d", child.name, child.spare.pid)

    def restart(self, child: Child) -> None:
        """Starts a dead child again with the same command and environment, from its spare if it has one
        ready; its log goes on."""
        child.restarts += 1
        child.died_at, child.reported = None, False
        spare, child.spare = child.spare, None
        with open_log(child.log_path, "ab") as out:
            out.write(f"\n--- esiaf: restart {child.restarts}{' (its spare)' if spare else ''} ---\n".encode())
        if spare is not None and spare.poll() is None and _release(spare):
            child.process = spare
        else:
            child.process = self._spawn(child.command, child.env, child.log_path, "ab")
        child.started_at = time.monotonic()
        log.info("restarted service=%s pid=%d restarts=%d from_spare=%s", child.name, child.process.pid,
                 child.restarts, child.process is spare)

    def restart_when_due(self, child: Child) -> None:
        """A service died: say which and why, restart it after a back-off (doubling from
        RESTART_BACKOFF_S), and give up with its log's tail after MAX_RESTARTS deaths in a row, each
        within STABLE_AFTER_S of its start (a crash loop); a death after a longer run counts as the
        first, so that a long --serve run survives a rare crash."""
        now = time.monotonic()
        if child.died_at is None:
            child.died_at = now
            if now - child.started_at >= STABLE_AFTER_S:
                child.restarts = 0
            last_line = child.tail(1).strip()
            if child.restarts >= MAX_RESTARTS:
                raise LaunchError(f"{self.failure(child)}\n(not restarted: it died {child.restarts + 1} times)")
            err(f"esiaf: service {child.name} {child.how_it_ended()}"
                f"{f' ({last_line})' if last_line else ''}; restarting it in {child.restart_delay_s():.1f} s "
                f"({child.restarts + 1} of {MAX_RESTARTS})")
        if now - child.died_at >= child.restart_delay_s():
            self.restart(child)

    def refusals(self) -> list[tuple[Child, str]]:
        """What each child has refused since the last call, as its log says (see Child.new_refusals)."""
        return [(child, line) for child in self.children for line in child.new_refusals()]

    def exited(self) -> list[Child]:
        return [c for c in self.children if c.process.poll() is not None]

    def failure(self, child: Child) -> str:
        """Why ``child`` ended: with code 2 (a bad setting or input, the service's one line, esiaf/runner.py)
        that line; otherwise the end of its log."""
        last = child.tail(1).strip()
        if child.process.returncode == 2 and last and "Traceback" not in child.tail():
            return f"service {child.name} exited with code 2: {last} (its log: {child.log_path})"
        return (f"service {child.name} {child.how_it_ended()}; "
                f"its log ({child.log_path}) ends:\n{child.tail()}")

    def stop(self, timeout_s: float = 5.0) -> None:
        for child in self.children:
            if child.spare is not None:  # never released: it has nothing to finish
                child.spare.kill()
                child.spare.wait()
                child.spare = None
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


def _release(spare: subprocess.Popen) -> bool:
    """Tells a waiting spare to run (a line on its stdin); False if it is gone."""
    assert spare.stdin is not None  # started with stdin=PIPE
    try:
        spare.stdin.write(b"run\n")
        spare.stdin.close()
    except OSError:
        return False
    return True


def open_log(path: Path, mode: str) -> IO[bytes]:
    """A service's log, readable by its owner only (0600, whatever the umask, and also if it was there
    before): what a service logs may say more than other users of the machine should read."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_APPEND if mode == "ab" else os.O_TRUNC)
    descriptor = os.open(path, flags, 0o600)
    os.fchmod(descriptor, 0o600)
    return os.fdopen(descriptor, mode)


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


def fixed_ports(workdir: Path, names: tuple[str, ...] = ("control", "results")) -> dict[str, int]:
    """The orchestrator's ZeroMQ ports of this workdir: chosen free once, kept in ports.json, so an
    orchestrator restarted in the same workdir comes back where its components push results."""
    path = workdir / "ports.json"
    try:
        ports = {name: int(port) for name, port in json.loads(path.read_text()).items() if name in names}
    except (OSError, ValueError, AttributeError, TypeError):
        ports = {}
    for name in names:
        if name not in ports or not _port_free(ports[name]):
            ports[name] = _any_free_port()
    workdir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(ports))
    return ports


def _port_free(port: int) -> bool:
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _any_free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class OrchestratorClient:
    def __init__(self, url: str):
        self.url = url.rstrip("/")
        self._http = OrchestratorHTTP(self.url, timeout_s=2.0)

    def healthy(self) -> bool:
        return self._http.get(f"{self.url}/health").status_code == 200

    def recovered(self) -> list[str]:
        """The orchestrator's report of a ``--recover`` that repaired its database (empty if sound)."""
        response = self._http.get(f"{self.url}/health")
        return [str(line) for line in response.json().get("recovered") or []] if response.status_code == 200 else []

    def health_problem(self) -> str:
        """'' while healthy, else what /health says is wrong."""
        response = self._http.get(f"{self.url}/health")
        if response.status_code == 200:
            return ""
        try:
            return str(response.json().get("detail") or response.status_code)
        except ValueError:
            return f"/health answered {response.status_code}"

    def components(self) -> list[dict[str, Any]]:
        response = self._http.get(f"{self.url}/components")
        response.raise_for_status()
        return response.json()["items"]

    def component(self, name: str) -> dict[str, Any] | None:
        return next((c for c in self.components() if c.get("name") == name), None)

    def instance(self, component_id: str) -> dict[str, Any] | None:
        """The live component registered under this id (one of several instances of a service)."""
        return next((c for c in self.components() if c.get("component_id") == component_id
                     and c.get("status") == "alive"), None)

    def by_pid(self, pid: int) -> dict[str, Any] | None:
        """The live component a process registered (plug-ins: their name is their own)."""
        return next((c for c in self.components() if c.get("pid") == pid and c.get("status") == "alive"), None)

    def report_dead(self, pid: int) -> str | None:
        """Tells the orchestrator that the process ``pid`` died, so that its components are dead now and
        not only once silent for dead_after_s (a host and its guests: each of them); their ids, or None
        (none was registered, they had left cleanly, or the orchestrator is not there: then their
        silence will tell)."""
        reported = []
        try:
            for component in self.components():
                if component.get("pid") == pid and component.get("status") == "alive":
                    self._http.post(f"{self.url}/components/{component['component_id']}/dead").raise_for_status()
                    reported.append(str(component["component_id"]))
        except httpx.HTTPError as exc:
            log.debug("could not report pid=%d dead: %s", pid, exc)
        return ", ".join(reported) or None

    def fusions(self) -> list[dict[str, Any]]:
        response = self._http.get(f"{self.url}/fusions")
        response.raise_for_status()
        return response.json()["items"]

    def put_fusions(self, fusions: list[dict[str, Any]]) -> None:
        response = self._http.put(f"{self.url}/fusions", json={"items": fusions})
        if response.status_code != 200:
            raise LaunchError(f"the orchestrator refused the fusions {fusions}: {response.text}")

    def topics(self) -> list[dict[str, Any]]:
        response = self._http.get(f"{self.url}/topics")
        response.raise_for_status()
        return response.json()["items"]

    def stream(self, stream_id: str) -> dict[str, Any] | None:
        response = self._http.get(f"{self.url}/streams/{quote(stream_id, safe='')}")
        if response.status_code == 404:
            return None
        response.raise_for_status()
        return response.json()

    def fused(self, stream_id: str) -> list[dict[str, Any]]:
        """Every fused result of a stream (``GET /fused``, page by page), each at its latest revision."""
        items: list[dict[str, Any]] = []
        after_id = 0
        while True:
            response = self._http.get(f"{self.url}/fused", params={"stream": stream_id, "after_id": after_id,
                                                                   "limit": 1000})
            response.raise_for_status()
            page = response.json()
            items.extend(page["items"])
            if len(page["items"]) < 1000 or page.get("next_after_id") is None:
                return items
            after_id = page["next_after_id"]

    def announce(self, stream_id: str, info: dict[str, Any]) -> None:
        """Announces a stream ahead of its source (which announces it again, with its start)."""
        response = self._http.put(f"{self.url}/streams/{quote(stream_id, safe='')}",
                                  json={"start_ns": time.time_ns(), "info": info})
        if response.status_code != 200:
            raise LaunchError(f"the orchestrator refused to announce stream {stream_id}: {response.text}")

    def close(self) -> None:
        self._http.close()

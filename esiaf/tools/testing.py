"""Test helpers for ESIAF's own tests and for components' integration tests.

Real parts only: the launcher and the orchestrator as processes on random
loopback ports, a real SQLite file, and polling with deadlines instead of
fixed sleeps. ``shared_data`` and ``need_flite`` skip (pytest) with the reason
when the shared test data or Debian's flite is absent. One analyser in-process
on a WAV file: ``esiaf.testing``.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]  # the repository (tests run from a checkout)
# ../shared/data beside the repository; ESIAF_SHARED_DATA points elsewhere (e.g. from a git worktree)
SHARED_DATA = Path(os.environ.get("ESIAF_SHARED_DATA") or REPO.parent / "shared" / "data")


def shared_data(relative: str) -> Path:
    """A file of ../shared/data, or a skip that says it is missing."""
    import pytest
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"test data {path} is absent (the shared data folder belongs beside the repository)")
    return path


def need_flite() -> None:
    import pytest
    if not shutil.which("flite"):
        pytest.skip("Debian's flite is not installed (setup.sh installs it)")


def is_spare(process: Any) -> bool:
    """A psutil process that is a waiting spare of a service (esiaf/tools/launcher.py), not the service:
    its process name says so while it waits (esiaf/runner.py SPARE_NAME)."""
    try:
        return bool(process.name() == "esiaf-spare")
    except Exception:  # gone meanwhile: not one to take for the service either
        return True


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def half_sent_requests(host: str, port: int, count: int, source: str = "127.0.0.2",
                       timeout_s: float = 2.0) -> list[socket.socket]:
    """``count`` connections to ``host:port`` from the loopback address ``source``, each holding an HTTP
    request whose headers never end (``GET /health HTTP/1.1`` and one header line): what a peer without
    the token can do to take a server's file descriptors. Connections the server closed or never took
    in ``timeout_s`` are not returned; the caller closes the others."""
    held = []
    for _ in range(count):
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s, source_address=(source, 0))
        except OSError:
            continue
        try:
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: esiaf\r\n")
        except OSError:
            sock.close()
            continue
        held.append(sock)
    return held


def file_limit(count: int):
    """A ``preexec_fn`` giving a child process a limit of ``count`` open files (soft and hard, as
    ``ulimit -n``), the limit many Linux services get."""
    def limit() -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_NOFILE, (count, count))
    return limit


def normalise(text: str) -> str:
    return " ".join(re.sub(r"[^a-z0-9' ]+", " ", text.lower()).split())


class Launcher:
    """``esiaf run`` as a child process, its stdout JSON lines collected as they come."""

    def __init__(self, args: list[str], workdir: Path, env: dict[str, str] | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.workdir = workdir
        cmd = [sys.executable, "-m", "esiaf", "run", "--port", str(self.port), "--workdir", str(workdir), *args]
        self.process = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                        env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})})
        self.lines: list[dict] = []
        self.stderr: list[str] = []
        self._new_line = threading.Condition()
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def _read_stdout(self) -> None:
        assert self.process.stdout is not None  # stdout=PIPE
        for line in self.process.stdout:
            with self._new_line:
                self.lines.append(json.loads(line) if line.startswith("{") else {"text": line.rstrip("\n")})
                self._new_line.notify_all()

    def _read_stderr(self) -> None:
        assert self.process.stderr is not None  # stderr=PIPE
        for line in self.process.stderr:
            self.stderr.append(line)

    @property
    def token(self) -> str:
        """The token ``esiaf run`` made for this run (in its workdir once it has started)."""
        return (self.workdir / "token").read_text().strip()

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def ws_url(self, path: str) -> str:
        """A websocket URL of this run's orchestrator, with the token (``path`` may hold a query)."""
        return self.url.replace("http", "ws") + path + ("&" if "?" in path else "?") + f"token={self.token}"

    def wait_for_line(self, predicate, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        with self._new_line:
            while True:
                for line in self.lines:
                    if predicate(line):
                        return line
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.process.poll() is not None:
                    raise AssertionError(f"no such line after {timeout_s} s; stdout={self.lines} "
                                         f"stderr={''.join(self.stderr)}")
                self._new_line.wait(min(remaining, 0.2))

    def describe(self) -> str:
        """Whether ``esiaf run`` is still running, and the end of what it said on stderr: for failures."""
        code = self.process.poll()
        state = "still running" if code is None else f"exited with {code}"
        return f"esiaf run {state}; its stderr ends:\n{''.join(self.stderr[-30:])}"

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait()



def poll(condition, timeout_s: float, interval_s: float = 0.05):
    """Calls ``condition`` until it returns something truthy, or fails after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last_error = None
    while time.monotonic() < deadline:
        try:
            value = condition()
            if value:
                return value
        except Exception as exc:  # not up yet
            last_error = exc
        threading.Event().wait(interval_s)
    raise AssertionError(f"condition not met within {timeout_s} s (last error: {last_error})")


def refused_peers(metrics_text: str, socket: str, *reasons: str) -> float:
    """``esiaf_refused_peers_total`` in a ``GET /metrics`` answer: the handshakes one socket refused
    for these reasons (every reason if none is named)."""
    from prometheus_client.parser import text_string_to_metric_families
    return sum(sample.value for family in text_string_to_metric_families(metrics_text) for sample in family.samples
               if sample.name == "esiaf_refused_peers_total" and sample.labels["socket"] == socket
               and (not reasons or sample.labels["reason"] in reasons))


def refused_control(metrics_text: str, *reasons: str) -> float:
    """``esiaf_refused_control_messages_total`` in a ``GET /metrics`` answer: the control messages
    refused for these reasons (``no_key``, ``wrong_key``, ``wrong_peer_key``; every reason if none)."""
    from prometheus_client.parser import text_string_to_metric_families
    return sum(sample.value for family in text_string_to_metric_families(metrics_text) for sample in family.samples
               if sample.name == "esiaf_refused_control_messages_total"
               and (not reasons or sample.labels["reason"] in reasons))


def refused_messages(metrics_text: str, *reasons: str) -> float:
    """``esiaf_refused_messages_total`` in a ``GET /metrics`` answer: results-plane messages refused
    for these reasons (``no_key``, ``wrong_key``, ``old_key``, ``wrong_peer_key``...; every reason if none)."""
    from prometheus_client.parser import text_string_to_metric_families
    return sum(sample.value for family in text_string_to_metric_families(metrics_text) for sample in family.samples
               if sample.name == "esiaf_refused_messages_total" and (not reasons or sample.labels["reason"] in reasons))


def signed_result(registration: dict[str, Any], result: Any) -> list[bytes]:
    """The frames of ``result`` (a pb.Result) as the SDK sends it for ``registration`` (the answer of
    ``POST /components``): named by its instance, with the registration's key id and MAC."""
    from types import SimpleNamespace

    from esiaf.binding import signed
    result.instance = registration["component_id"]
    return signed(b"result", result.SerializeToString(),
                  SimpleNamespace(key_id=registration["key_id"], control_key=registration["control_key"]))


class Orchestrator:
    """The real orchestrator as a process on random loopback ports, with a real SQLite file."""

    def __init__(self, tmp_path: Path, config: dict | None = None, env: dict[str, str] | None = None,
                 ca: Path | None = None, open_files: int | None = None):
        """``config``: orchestrator settings written to a YAML file (fusions, timeouts, ...);
        ``env``: more environment variables for its process (ESIAF_TOKEN, ESIAF_CURVE_DIR, ...);
        ``ca``: with ``tls_cert`` in ``config``, the CA file its certificate is checked against;
        ``open_files``: its limit of open files (soft and hard), if not this process's."""
        import httpx
        import yaml
        self.port = free_port()
        secure = "s" if config and config.get("tls_cert") else ""
        self.url = f"http{secure}://127.0.0.1:{self.port}"
        self.ws_url = f"ws{secure}://127.0.0.1:{self.port}"
        self.db_path = tmp_path / "o.db"
        self.env = env or {}
        self.preexec = file_limit(open_files) if open_files else None
        self.config_args: list[str] = []
        if config is not None:
            config_path = tmp_path / "orchestrator.yaml"
            config_path.write_text(yaml.safe_dump(config))
            self.config_args = ["--config", str(config_path)]
        self.log = (tmp_path / "orchestrator.log").open("ab")
        verify = httpx.create_ssl_context()
        if ca is not None:
            verify.load_verify_locations(cafile=str(ca))
        self.http = httpx.Client(base_url=self.url, timeout=5, verify=verify)
        self.process: subprocess.Popen  # start() makes it
        self.start()

    def start(self, *args: str) -> None:
        """Starts it (again: same HTTP port and database, new random ZeroMQ ports), with more
        command-line ``args`` (e.g. ``--recover``) if given."""
        env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0",
               "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0", **self.env}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(self.port), "--db", str(self.db_path),
             *self.config_args, *args],
            cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT, preexec_fn=self.preexec)
        poll(lambda: self.http.get("/health").status_code == 200, timeout_s=30)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait()

    def component(self, name: str) -> dict | None:
        return next((c for c in self.http.get("/components").json()["items"] if c["name"] == name), None)

    def close(self) -> None:
        self.http.close()
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)
        self.log.close()

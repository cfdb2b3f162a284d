"""No token in a log, and logs readable by their owner only: the orchestrator as a process, a real
websocket client that carries the token in its URL as the dashboard does, the launcher's real log files."""
from __future__ import annotations

import os
import stat

from websockets.sync.client import connect

from esiaf.tools.launcher import Supervisor
from esiaf.tools.testing import Orchestrator, poll

TOKEN = "log-secret-token-0123456789"


def test_the_token_of_a_dashboard_websocket_url_is_not_logged(tmp_path):
    orchestrator = Orchestrator(tmp_path, env={"ESIAF_TOKEN": TOKEN})
    try:
        with connect(f"{orchestrator.ws_url}/ws/fused?stream=a&token={TOKEN}", open_timeout=10):
            pass
        log = tmp_path / "orchestrator.log"
        accepted = poll(lambda: [line for line in log.read_text().splitlines() if "WebSocket /ws/fused" in line], 10)
        assert "token=[redacted]" in accepted[0], accepted
        assert TOKEN not in log.read_text()
    finally:
        orchestrator.close()


def test_service_logs_are_made_readable_by_their_owner_only(tmp_path):
    (tmp_path / "logs").mkdir()
    before = tmp_path / "logs" / "old.log"
    before.write_text("a log of an earlier run, readable by all\n")
    before.chmod(0o644)
    umask = os.umask(0o022)
    supervisor = Supervisor(tmp_path)
    try:
        for name in ("new", "old"):
            supervisor.start(name, target=["-c", "print('started')"])
        poll(lambda: len(supervisor.exited()) == 2, timeout_s=30)
        supervisor.restart(supervisor.children[0])
    finally:
        os.umask(umask)
        supervisor.stop()
    for child in supervisor.children:
        assert stat.S_IMODE(child.log_path.stat().st_mode) == 0o600, child.log_path
        assert "started" in child.log_path.read_text()
    assert stat.S_IMODE((tmp_path / "logs").stat().st_mode) == 0o700

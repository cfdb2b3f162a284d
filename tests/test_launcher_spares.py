"""The launcher's spares (esiaf/tools/launcher.py): a service that keeps one gets its first spare as
soon as the pipeline is up, not SPARE_AFTER_S later; after a restart the spare waits SPARE_AFTER_S
again (a crash loop does not start a spare per death). Real processes: a script that waits."""
from __future__ import annotations

import time

from esiaf.tools.launcher import SPARE_AFTER_S, Supervisor


def started(tmp_path):
    """A supervisor with one child that keeps a spare: a script that waits a minute."""
    script = tmp_path / "waiter.py"
    script.write_text("import time\ntime.sleep(60)\n")
    supervisor = Supervisor(tmp_path)
    child = supervisor.start("waiter", target=[str(script)], spare=True)
    return supervisor, child


def test_the_first_spare_starts_once_the_pipeline_is_up(tmp_path):
    supervisor, child = started(tmp_path)
    try:
        supervisor.keep_spares()
        assert child.spare is None  # not up yet, and not SPARE_AFTER_S old
        supervisor.ready()
        assert child.spare is not None and child.spare.poll() is None
        assert child.spare.pid != child.process.pid
    finally:
        supervisor.stop()
    assert child.spare is None  # a spare never released is killed at the end


def test_after_a_restart_the_next_spare_waits(tmp_path):
    supervisor, child = started(tmp_path)
    try:
        supervisor.ready()
        spare = child.spare
        child.process.kill()
        child.process.wait()
        supervisor.restart(child)
        assert child.process is spare and child.spare is None  # the spare took over
        supervisor.keep_spares()
        assert child.spare is None  # restarted: the next spare after SPARE_AFTER_S
        child.started_at = time.monotonic() - SPARE_AFTER_S
        supervisor.keep_spares()
        assert child.spare is not None and child.spare.poll() is None
    finally:
        supervisor.stop()

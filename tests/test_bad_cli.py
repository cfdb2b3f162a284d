"""Every bad value of bench/bad_cli.py's table, given to ``esiaf run`` or to a service as a process:
one line on stderr, exit code 2, no traceback, and without waiting for anything (before anything
starts; a setting only one service knows is checked by that service's settings model, loaded, not started).
How long each answer takes (the 2 s target) is measured by ``python -m bench.bad_cli``, not here."""
from __future__ import annotations

import pytest

from bench.bad_cli import CASES, Case, run_case
from esiaf.tools.testing import free_port

NO_WAIT_S = 30.0  # a wait for something that never comes took 33 to 60 s (a loaded machine: 15 s at most)


@pytest.mark.parametrize("case", CASES, ids=[case.name for case in CASES])
def test_a_bad_value_is_one_line_and_exit_2(case: Case, tmp_path):
    port = free_port()
    outcome = run_case(case, tmp_path, port=port, timeout_s=120)
    assert outcome.code == 2, outcome.lines
    assert not outcome.traceback, outcome.lines
    assert len(outcome.lines) == 1, outcome.lines
    assert outcome.wall_s <= NO_WAIT_S, outcome

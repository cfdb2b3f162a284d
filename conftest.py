"""Fixtures shared by every test folder (tests/, esiaf_services/*/tests/); the helpers are in esiaf.tools.testing."""
from __future__ import annotations

import pytest

from esiaf.tools.testing import Launcher, Orchestrator


@pytest.fixture
def launch(tmp_path):
    """Starts ``esiaf run`` with the given arguments; every launcher is stopped at the end."""
    launchers: list[Launcher] = []

    def start(*args: str, env: dict[str, str] | None = None) -> Launcher:
        launcher = Launcher(list(args), tmp_path / f"run{len(launchers)}", env)
        launchers.append(launcher)
        return launcher

    yield start
    for launcher in launchers:
        launcher.stop()


@pytest.fixture
def orchestrator(tmp_path):
    orch = Orchestrator(tmp_path)
    yield orch
    orch.close()

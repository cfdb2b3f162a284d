"""Fixtures: the real app on a random loopback port, a ZeroMQ context, fake components."""
from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
import zmq

from esiaf_services.orchestrator.settings import OrchestratorSettings
from esiaf_services.orchestrator.tests.helpers import FakeComponent, RunningOrchestrator, component_body


@pytest.fixture
def make_orchestrator(tmp_path) -> Iterator[Callable[..., RunningOrchestrator]]:
    started: list[RunningOrchestrator] = []

    def make(**overrides: Any) -> RunningOrchestrator:
        # these tests time beats and deaths at 0.5 / 2.5 s, quicker than the defaults (2 / 8 s)
        values = {"control_port": 0, "results_port": 0, "heartbeat_interval_s": 0.5, "dead_after_s": 2.5,
                  "db_path": str(tmp_path / f"esiaf{len(started)}.db"), **overrides}
        running = RunningOrchestrator(OrchestratorSettings(**values)).start()
        started.append(running)
        return running

    yield make
    for running in started:
        running.stop()


@pytest.fixture
def orch(make_orchestrator) -> RunningOrchestrator:
    return make_orchestrator()


@pytest.fixture
def http(orch) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=orch.url, timeout=5.0) as client:
        yield client


@pytest.fixture
def zctx() -> Iterator[zmq.Context]:
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def component(zctx, http) -> Iterator[Callable[..., FakeComponent]]:
    made: list[FakeComponent] = []

    def make(name: str, **kwargs: Any) -> FakeComponent:
        fake = FakeComponent(zctx, http, component_body(name, **kwargs))
        made.append(fake)
        return fake

    yield make
    for fake in made:
        fake.close()

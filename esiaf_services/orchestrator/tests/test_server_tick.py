"""uvicorn's main loop in the orchestrator: it does not wake while idle (uvicorn's own wakes ten times a
second), the Date header is still current whenever a response is made, and the loop ends at
once when told to."""
from __future__ import annotations

import asyncio
import time
from email.utils import parsedate_to_datetime

import uvicorn

from esiaf_services.orchestrator.server import _Server


async def app(scope, receive, send) -> None:  # never called: no request is made
    raise AssertionError("no request expected")


def test_the_main_loop_sleeps_until_told_to_exit_and_the_date_is_current_when_read():
    async def run() -> tuple[list[int], list[float], float]:
        config = uvicorn.Config(app, log_config=None)
        config.load()
        server = _Server(config)
        ticks: list[int] = []
        dates: list[float] = []
        on_tick = server.on_tick

        async def counted(counter: int) -> bool:
            ticks.append(counter)
            return await on_tick(counter)

        server.on_tick = counted  # type: ignore[method-assign]
        loop = asyncio.create_task(server.main_loop())
        for _ in range(3):
            await asyncio.sleep(1.0)
            headers = dict(server.server_state.default_headers)  # what a response is made with
            dates.append(parsedate_to_datetime(headers[b"date"].decode()).timestamp() - time.time())
            assert headers[b"server"] == b"uvicorn"  # the configured headers stay
        asked = time.monotonic()
        server.exit()
        await asyncio.wait_for(loop, 1.0)
        return ticks, dates, time.monotonic() - asked

    ticks, dates, took_s = asyncio.run(run())
    assert len(ticks) == 2  # at the start, and when told to exit: nothing in the 3 s between
    assert all(-1.5 < offset <= 0.0 for offset in dates)  # current to the second each time
    assert took_s < 0.2

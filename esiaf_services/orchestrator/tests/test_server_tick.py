"""uvicorn's main loop in the orchestrator: it wakes once a second, not ten times (issue 18), still
renews the Date header every second, and ends at once when told to."""
from __future__ import annotations

import asyncio
import time

import uvicorn

from esiaf_services.orchestrator.server import TICK_S, _Server


async def app(scope, receive, send) -> None:  # never called: no request is made
    raise AssertionError("no request expected")


def test_the_main_loop_ticks_once_a_second_renews_the_date_and_exits_at_once():
    async def run() -> tuple[list[int], list[bytes], float]:
        config = uvicorn.Config(app, log_config=None)
        config.load()
        server = _Server(config)
        ticks: list[int] = []
        dates: list[bytes] = []
        on_tick = server.on_tick

        async def counted(counter: int) -> bool:
            ticks.append(counter)
            done = await on_tick(counter)
            dates.append(dict(server.server_state.default_headers)[b"date"])
            return done

        server.on_tick = counted  # type: ignore[method-assign]
        loop = asyncio.create_task(server.main_loop())
        await asyncio.sleep(2.5 * TICK_S)
        asked = time.monotonic()
        server.exit()
        await asyncio.wait_for(loop, 1.0)
        return ticks, dates, time.monotonic() - asked

    ticks, dates, took_s = asyncio.run(run())
    # at 0, 1 and 2 s, and once more when told to exit (uvicorn's own loop: 26 ticks)
    assert len(ticks) == 4 and all(counter % 10 == 0 for counter in ticks)
    assert len(set(dates)) >= 2  # renewed each tick (the date has a resolution of a second)
    assert took_s < 0.2 * TICK_S

"""websocket /ws/fused: the stored fused results after ``after_id``, then live ones, stream events and
barge-in events (without the robot's own voice unless ``include_robot=true``)."""
from __future__ import annotations

import asyncio
import contextlib
import json
import logging

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect

from ..core import Orchestrator
from ..planes.hub import CLOSE_TOO_SLOW, Subscriber, withdrawal
from .deps import MAX_ID

log = logging.getLogger(__name__)
router = APIRouter(tags=["fused"])

BACKLOG_PAGE = 500
CLOSE_TIMEOUT_S = 1.0


@router.websocket("/ws/fused")
async def ws_fused(websocket: WebSocket,
                   stream: str | None = Query(None, description="stream_id"),
                   fusion: str | None = Query(None, description="fusion name"),
                   after_id: int | None = Query(
                       None, ge=0, le=MAX_ID, description="first the latest revision of each stored fused "
                                               "result with a larger id"),
                   after_seq: int | None = Query(
                       None, ge=0, le=MAX_ID, description="first every publication (each revision) with a "
                                               "larger seq: resume without missing revisions "
                                               "(after_id is then ignored)"),
                   partials: bool = Query(False, description="also the recognisers' partial results while "
                                          "an utterance goes on (`partial` events, never stored)"),
                   include_robot: bool = Query(False, description="also fused results of the robot's own voice")
                   ) -> None:
    core: Orchestrator = websocket.app.state.core
    client = f"{websocket.client.host}:{websocket.client.port}" if websocket.client else "-"
    # Subscribe before the client can see the connection open, and before reading the
    # backlog: nothing published meanwhile is missed.
    subscriber = core.hub.subscribe(client, stream, fusion, partials, include_robot)
    tasks: set[asyncio.Task] = set()
    try:
        await websocket.accept()
        log.info("event=ws_connected client=%s stream=%s fusion=%s after_id=%s",
                 client, stream or "-", fusion or "-", "-" if after_id is None else after_id)
        tasks = {asyncio.create_task(_send(websocket, core, subscriber, after_id, after_seq)),
                 asyncio.create_task(_until_disconnect(websocket)),
                 asyncio.create_task(subscriber.dropped.wait())}
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        core.hub.unsubscribe(subscriber)
        for task in tasks:
            task.cancel()
        for outcome in await asyncio.gather(*tasks, return_exceptions=True):
            if isinstance(outcome, Exception) and not isinstance(outcome, WebSocketDisconnect):
                log.warning("event=ws_failed client=%s reason=%r", client, outcome)
    if subscriber.dropped.is_set():
        with contextlib.suppress(Exception):  # the client is gone or stuck: nothing more to tell it
            await asyncio.wait_for(
                websocket.close(code=CLOSE_TOO_SLOW, reason=subscriber.close_reason),
                CLOSE_TIMEOUT_S)
    log.info("event=ws_disconnected client=%s", client)


async def _until_disconnect(websocket: WebSocket) -> None:
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass  # clients have nothing to say


async def _send(websocket: WebSocket, core: Orchestrator, subscriber: Subscriber,
                after_id: int | None, after_seq: int | None) -> None:
    sent: dict[int, int] = {}  # fused id -> revision sent from the backlog
    last_seq = after_seq or 0
    while after_seq is not None:
        rows = core.store.publications(after_seq=last_seq, fusion=subscriber.fusion, stream=subscriber.stream,
                                       limit=BACKLOG_PAGE, include_robot=subscriber.include_robot)
        for seq, text in rows:
            if not subscriber.include_robot and '"robot"' in text and (fused := json.loads(text))["source"] == "robot":
                text = withdrawal(fused)  # the robot's revision of a person's: it withdraws that
            await websocket.send_text(text)
            last_seq = seq
        if len(rows) < BACKLOG_PAGE:
            break
    cursor = after_id if after_seq is None else None  # after_seq, if given, has sent it all
    while cursor is not None:
        page = core.store.query_fused(fusion=subscriber.fusion, stream=subscriber.stream, after_id=cursor,
                                      limit=BACKLOG_PAGE, include_robot=subscriber.include_robot)
        for text in page.items:
            await websocket.send_text(text)
        sent.update(page.revisions)
        cursor = page.next_after_id if len(page.items) == BACKLOG_PAGE else None
    while True:
        message = await subscriber.queue.get()
        if message.fused_id is not None and (sent.get(message.fused_id, 0) >= message.revision
                                             or message.seq <= last_seq):
            continue  # already sent from the backlog
        await websocket.send_text(message.text_for(subscriber.include_robot))

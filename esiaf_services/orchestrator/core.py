"""The orchestrator's state and background tasks, wired together; runs inside the event loop.

This is the one place that builds the parts (the registry and fusion engine, the store, the
ZeroMQ planes) and hands each its collaborators and callbacks through its constructor.
"""
from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import secrets
import signal
import sqlite3
import time
from collections import Counter
from typing import Any, TypeVar

import zmq
import zmq.asyncio

from esiaf import auth, keys
from esiaf.transport import keep_alive

from .fusion.engine import FusionEngine
from .planes.clocks import StreamClocks
from .planes.control import ControlPlane
from .planes.hub import Hub
from .planes.ingest import Ingest
from .planes.metrics import Metrics
from .planes.players import Players
from .planes.results import ResultsLoop
from .planes.zap import Guard
from .registry.components import Component, Registry
from .registry.negotiation import Format
from .settings import OrchestratorSettings
from .store.database import RECOVER_HINT, Checkpointer, Store, StoreError, is_corrupt_error

log = logging.getLogger(__name__)

LIVENESS_MAX_SLEEP_S = 5.0  # the liveness task wakes when the first component may be dead, at the latest this
CHECKPOINT_INTERVAL_S = 1.0  # the SQLite WAL is copied into the database this long after a write, at most this often
ANY_HOST = ("0.0.0.0", "*", "")


class StartupError(Exception):
    """The orchestrator cannot start: one line that says why and what to do."""


T = TypeVar("T")


def _running(part: T | None, name: str) -> T:
    """One of the parts the orchestrator makes at start(): there only while it runs."""
    if part is None:
        raise RuntimeError(f"the orchestrator's {name} is used while it is not running "
                           "(before start() or after stop())")
    return part


def zmq_host(host: str) -> str:
    if host in ANY_HOST:
        return "*"
    return f"[{host}]" if ":" in host else host


class Orchestrator:
    def __init__(self, settings: OrchestratorSettings, *, fresh: bool = False) -> None:
        self.settings = settings
        self.fresh = fresh
        self.recovered: list[str] = []  # the report of a --recover that repaired the database at start-up
        # HTTP connections closed below the app (connections.py), by reason: peer_limit, total_limit,
        # request_timeout; the server counts them here, GET /metrics shows them
        self.http_refused: Counter[str] = Counter()
        self.registry = Registry(settings.format_strategy)
        self.clocks = StreamClocks(self.registry)
        self.hub = Hub()
        # made by start(), until stop(): read them through the properties below
        self._store: Store | None = None
        self._control: ControlPlane | None = None
        self._ingest: Ingest | None = None
        self._players: Players | None = None
        self._results: ResultsLoop | None = None
        self.metrics = Metrics()
        self.control_endpoint = ""
        self.results_endpoint = ""
        self._ctx: zmq.asyncio.Context | None = None
        self._guard: Guard | None = None
        self._tasks: list[asyncio.Task] = []
        self._pushes: set[asyncio.Task] = set()  # state pushes under way (_push_soon)
        self._liveness_news = asyncio.Event()  # a component registered, or its death may be due sooner
        self._written = asyncio.Event()  # the store wrote something: the checkpoint task copies the WAL
        self.closing = asyncio.Event()  # set when the server begins to shut down: long polls answer at once

    # the parts start() makes; the REST API, the metrics and the tasks use them only while running
    @property
    def store(self) -> Store:
        return _running(self._store, "store")

    @property
    def control(self) -> ControlPlane:
        return _running(self._control, "control")

    @property
    def ingest(self) -> Ingest:
        return _running(self._ingest, "ingest")

    @property
    def players(self) -> Players:
        return _running(self._players, "players")

    @property
    def guard(self) -> Guard:
        return _running(self._guard, "guard")

    # lifecycle
    async def start(self) -> None:
        """Checks the fusions, binds the ZeroMQ sockets, opens the database, starts the tasks;
        raises StartupError (after cleaning up) if any of it fails."""
        try:
            self._start()
        except BaseException:
            await self.stop()
            raise
        self._tasks = [asyncio.create_task(self.control.run(), name="control"),
                       asyncio.create_task(_running(self._results, "results loop").run(), name="ingest"),
                       asyncio.create_task(self._watch_liveness(), name="liveness"),
                       asyncio.create_task(self._checkpoint(), name="checkpoint"),
                       *(asyncio.create_task(watch, name="zap") for watch in self.guard.watchers())]
        for task in self._tasks:
            task.add_done_callback(self._task_done)
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):  # not in the main thread
            asyncio.get_running_loop().add_signal_handler(signal.SIGHUP, self.guard.reload)
        log.info("event=orchestrator_ready control=%s results=%s zmq_auth=%s db=%s fusions=%s",
                 self.control_endpoint, self.results_endpoint, self.guard.mechanism, self.store.path,
                 ",".join(f.name for f in self.settings.fusions) or "-")

    def capture_offset_ns(self, stream_id: str) -> int:
        """Our clock minus the clock of the host that captures ``stream_id``: its announced source's
        offset, as that component measures it (0 while unknown)."""
        return self.clocks.capture_offset_ns(stream_id)

    def _start(self) -> None:
        settings = self.settings
        engine = FusionEngine(settings.fusions, allocate_id=lambda: self.store.allocate_fused_id(),
                              live_components=self.registry.live.values,
                              timeouts=settings.timeouts, capture_offset_ns=self.clocks.capture_offset_ns,
                              out_of_set_is_nothing=settings.robot_out_of_set_is_nothing)
        try:
            curve = keys.load(orchestrator=True)
        except keys.KeyFileError as exc:
            raise StartupError(str(exc)) from None
        self._ctx = zmq.asyncio.Context()
        # ZAP: the control and results sockets take only peers with an allowed key, or the token
        self._guard = Guard(self._ctx, settings.token or auth.token(), curve)
        self.guard.start()
        control_socket, self.control_endpoint = self._bind(zmq.ROUTER, settings.control_port,
                                                           "control", "control_port")
        results_socket, self.results_endpoint = self._bind(zmq.PULL, settings.results_port,
                                                           "results", "results_port")
        try:
            self._store = Store(settings.db_path, fresh=self.fresh, on_written=self._written.set)
        except StoreError as exc:
            raise StartupError(str(exc)) from None
        self.registry.secret = self.store.secret("control_keys", lambda: secrets.token_bytes(32))
        self._control = ControlPlane(control_socket, self.registry, bind_peer_key=self.guard.mechanism == "curve",
                                     intervals_s=(settings.heartbeat_interval_s, settings.idle_heartbeat_interval_s),
                                     disconnect_grace_s=settings.disconnect_grace_s,
                                     on_lost=self._disconnected, deadline_sooner=self._liveness_news.set)
        self._ingest = Ingest(self.store, engine, self.hub, self.registry, clocks=self.clocks,
                              metrics=self.metrics, stream_end_grace_s=self.settings.stream_end_grace_s,
                              stream_end_stall_grace_s=self.settings.stream_end_stall_grace_s,
                              on_assignments_changed=self._push_soon)
        self._players = Players(self.registry, self.control, settings.barge_in_policy, self.store)
        self._ingest.on_barge_in = self._players.barge_in
        self._results = ResultsLoop(results_socket, self._ingest, bind_peer_key=self.guard.mechanism == "curve")
        try:
            self.ingest.restore()
        except (sqlite3.Error, ValueError, KeyError) as exc:
            way_out = RECOVER_HINT if isinstance(exc, sqlite3.Error) and is_corrupt_error(exc) \
                else "start with --fresh to begin a new database"
            raise StartupError(f"cannot restore fusion state from {settings.db_path}: {exc} "
                               f"({way_out})") from None

    def _bind(self, kind: int, port: int, what: str,
              setting: str) -> tuple[zmq.asyncio.Socket, str]:
        host = zmq_host(self.settings.host)
        assert self._ctx is not None  # _start() makes it first
        socket = keep_alive(self._ctx.socket(kind))
        socket.setsockopt(zmq.LINGER, 0)
        self.guard.secure(socket, what, on_disconnect=self._control_disconnected if what == "control" else None)
        if host.startswith("["):
            socket.setsockopt(zmq.IPV6, 1)
        address = f"tcp://{host}:{port or '*'}"
        try:
            socket.bind(address)
        except zmq.ZMQError as exc:
            socket.close(linger=0)
            hint = ""
            if exc.errno == errno.EADDRINUSE:
                hint = (f" (is another orchestrator running? set {setting} in the config file "
                        f"or ESIAF_ORCHESTRATOR_{setting.upper()})")
            raise StartupError(f"cannot bind the {what} socket to {address}: "
                               f"{exc.strerror.lower()}{hint}") from None
        bound_port = socket.getsockopt_string(zmq.LAST_ENDPOINT).rsplit(":", 1)[1]
        advertised = self.settings.advertised_host()
        if ":" in advertised:
            advertised = f"[{advertised}]"
        return socket, f"tcp://{advertised}:{bound_port}"

    async def stop(self) -> None:
        """Stops the tasks, closes the sockets (linger 0) and the database. Safe to repeat."""
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._guard is not None:
            self._guard.stop()
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None
        if self._store is not None:
            self._store.close()
            self._store = None
            log.info("event=orchestrator_stopped")

    def _task_done(self, task: asyncio.Task) -> None:
        if not task.cancelled() and task.exception() is not None:
            log.critical("event=task_failed task=%s", task.get_name(), exc_info=task.exception())

    # what the REST API does
    async def register(self, *, name: str, kind: str, stream_id: str,
                       inputs: dict[str, Format], outputs: dict[str, Format],
                       audio_endpoint: str | None, host: str, pid: int | None,
                       info: dict[str, Any], audio_public_key: str | None = None,
                       instance: str | None = None, incarnation: str | None = None) -> Component:
        """Registers an instance (raises registry.TopicConflict, registry.InstanceConflict) and
        tells the others."""
        component, replaced = self.registry.register(
            name=name, kind=kind, stream_id=stream_id, inputs=inputs,
            outputs=outputs, audio_endpoint=audio_endpoint, host=host, pid=pid, info=info,
            audio_public_key=audio_public_key, instance=instance, incarnation=incarnation)
        self._liveness_news.set()
        if replaced is not None:
            log.info("event=component_registered_again component_id=%s name=%s", component.component_id, name)
        log.info("event=component_registered component_id=%s name=%s kind=%s stream_id=%s "
                 "inputs=%s outputs=%s audio_endpoint=%s host=%s pid=%s",
                 component.component_id, name, kind, stream_id,
                 ",".join(inputs) or "-", ",".join(outputs) or "-", audio_endpoint or "-",
                 host or "-", pid if pid is not None else "-")
        await self._after_change([])  # nothing stops waiting for anyone
        return component

    async def stream_announced(self, stream_id: str) -> None:
        """A stream starts: each replicated service gives it to one of its instances, at once."""
        if self.registry.add_stream(stream_id):
            await self.control.push_changes()

    def _push_soon(self) -> None:
        """Pushes changed states from synchronous code (the ingest): as a task of the loop."""
        task = asyncio.get_running_loop().create_task(self.control.push_changes(), name="push")
        self._pushes.add(task)
        task.add_done_callback(self._pushes.discard)

    async def remove(self, component_id: str) -> Component | None:
        return await self._gone(self.registry.remove(component_id), logging.INFO, "component_removed")

    async def declare_dead(self, component_id: str) -> Component | None:
        """A component whose process its launcher saw die: dead now, not dead_after_s later."""
        return await self._gone(self.registry.declare_dead(component_id), logging.WARNING, "component_dead",
                                " reported=launcher")

    def _control_disconnected(self, fd: int) -> None:
        if self._control is not None:
            self._control.disconnected(fd)

    async def _disconnected(self, component: Component) -> None:
        """Its control connection closed and it has not spoken since: its process died."""
        await self._gone(self.registry.declare_dead(component.component_id), logging.WARNING, "component_dead",
                         " reported=disconnected")

    async def _gone(self, component: Component | None, level: int, event: str, detail: str = "") -> Component | None:
        if component is not None:
            log.log(level, "event=%s component_id=%s name=%s%s", event, component.component_id, component.name, detail)
            await self._after_change([component])
        return component

    async def _after_change(self, gone: list[Component]) -> None:
        """Pushes changed states, and lets fusions and stream ends stop waiting for ``gone``."""
        await self.control.push_changes()
        if gone:
            self.ingest.components_gone(gone)

    async def _watch_liveness(self) -> None:
        """Declares silent components dead: it sleeps until the first of them may be (its last
        message plus dead_after_s, plus its idle interval's extra) or a dead one's stream-end grace runs
        out, or a registration or a faster beat makes a death due sooner; not on a fixed tick, and not
        at all while nothing is due."""
        while True:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._liveness_news.wait(), self._next_liveness_check_s())
            self._liveness_news.clear()
            dead = self.registry.expire(self.settings.dead_after_s)
            for component in dead:
                assert component.departed_ns is not None  # expire() sets it
                log.warning("event=component_dead component_id=%s name=%s silent_s=%.2f",
                            component.component_id, component.name,
                            (component.departed_ns - component.last_seen_ns) / 1e9)
            if dead:
                await self._after_change(dead)
            elif self._ingest is not None and self._ingest.streams.pending():
                self.ingest.check_stream_ends()  # a dead component's grace may have run out

    def _next_liveness_check_s(self) -> float | None:
        now_mono = time.monotonic()
        due = [c.silent_too_long_at(self.settings.dead_after_s) - now_mono for c in self.registry.live.values()]
        if self._ingest is not None and self._ingest.streams.pending():
            now_ns = time.time_ns()
            due += [(until - now_ns) / 1e9 for c in self.registry.departed.values()
                    if (until := self._ingest.held_until_ns(c)) is not None and now_ns < until]
        if not due:
            return None  # until a registration
        return min(max(min(due) + 0.005, 0.01), LIVENESS_MAX_SLEEP_S)

    async def _checkpoint(self) -> None:
        checkpointer = Checkpointer(self.store.path)
        checkpointed = -1
        job: asyncio.Future | None = None
        written = self._written  # set by the store, from the loop's thread: every write is
        try:
            while True:
                await written.wait()  # idle: asleep until something is written, not woken every second
                await asyncio.sleep(CHECKPOINT_INTERVAL_S)  # what is written meanwhile goes with it
                written.clear()
                if self.store.changes == checkpointed:
                    continue  # nothing written since the last one: no thread, no fsync
                checkpointed = self.store.changes
                job = asyncio.ensure_future(asyncio.to_thread(checkpointer.run))
                try:
                    await asyncio.shield(job)
                except sqlite3.Error as exc:
                    log.warning("event=checkpoint_failed reason=%r", str(exc))
        finally:
            if job is not None and not job.done():
                await asyncio.wait([job])  # never close the connection under the thread
            checkpointer.close()

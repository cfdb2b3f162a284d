"""Serving the app: the listening socket bound first, uvicorn, signals."""
from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import signal
import socket
import time
from collections.abc import Iterator
from email.utils import formatdate

import uvicorn
from uvicorn.server import ServerState

from .api.app import create_app
from .connections import ConnectionLimits, connections_allowed, guarded_protocol, raise_file_limit
from .core import Orchestrator, StartupError
from .settings import OrchestratorSettings

log = logging.getLogger(__name__)


def listen_socket(host: str, port: int) -> socket.socket:
    """Binds and listens on the HTTP port, or raises StartupError with one clear line."""
    where = f"{host}:{port}"
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as exc:
        raise StartupError(f"cannot listen on {where}: {exc.strerror} (check --host or "
                           "ESIAF_ORCHESTRATOR_HOST)") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        reason = (exc.strerror or str(exc)).lower()
        hint = ""
        if exc.errno == errno.EADDRINUSE:
            hint = (" (is another orchestrator running? set --port or ESIAF_ORCHESTRATOR_PORT)")
        elif exc.errno == errno.EACCES:
            hint = " (ports below 1024 need privileges; set --port or ESIAF_ORCHESTRATOR_PORT)"
        raise StartupError(f"cannot listen on {where}: {reason}{hint}") from None
    return sock


class _DatedState(ServerState):
    """uvicorn's shared server state, whose ``default_headers`` carry a Date made when they are read
    (for each request and websocket), renewed once a second at most: no tick is needed to keep it
    current. What uvicorn assigns (its own Date, if any, and the configured headers) is kept apart."""

    def __init__(self) -> None:
        super().__init__()
        self._dated = False  # uvicorn's on_tick decides (config.date_header)
        self._second = -1
        self._with_date: list[tuple[bytes, bytes]] = []

    @property  # type: ignore[override]  # an attribute in ServerState
    def default_headers(self) -> list[tuple[bytes, bytes]]:
        if not self._dated:
            return self._headers
        now = int(time.time())
        if now != self._second:
            self._second = now
            self._with_date = [(b"date", formatdate(now, usegmt=True).encode()), *self._headers]
        return self._with_date

    @default_headers.setter
    def default_headers(self, headers: list[tuple[bytes, bytes]]) -> None:
        self._dated = any(name == b"date" for name, _ in headers)
        self._headers = [(name, value) for name, value in headers if name != b"date"]
        self._second = -1


class _Server(uvicorn.Server):
    """uvicorn's server without its signal handling: serve() installs ours, which exit 0
    instead of re-raising the signal after shutdown. Its main loop does not wake while idle (uvicorn's
    wakes ten times a second, to renew the Date header and look whether to exit): the Date
    is made when read (:class:`_DatedState`), and :meth:`exit` ends the loop at once."""

    def __init__(self, config: uvicorn.Config) -> None:
        super().__init__(config)
        self.server_state = _DatedState()
        self._exit_now = asyncio.Event()  # bound to the loop that first waits on it

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield

    async def main_loop(self) -> None:
        # on_tick (counter 0) sets the default headers, and says whether to exit; limit_max_requests
        # and callback_notify, which it would also look after, are not used here
        while not await self.on_tick(0):
            await self._exit_now.wait()

    def exit(self, force: bool = False) -> None:
        """Starts the shutdown now (``force``: the second signal, without waiting for requests)."""
        self.force_exit = self.force_exit or force
        self.should_exit = True
        self._exit_now.set()


async def serve(settings: OrchestratorSettings, *, fresh: bool = False, recovered: list[str] | None = None) -> int:
    """Binds every port, then serves until SIGINT or SIGTERM; returns the exit code. ``recovered``:
    the report of a ``--recover`` that repaired the database, served by ``GET /health``."""
    file_limit = raise_file_limit()  # before anything is opened: the services' usual 1024 is not much
    sock = listen_socket(settings.host, settings.port)
    core = Orchestrator(settings, fresh=fresh)
    core.recovered = list(recovered or [])
    limits = ConnectionLimits(settings.request_timeout_s, settings.max_connections_per_peer,
                              connections_allowed(file_limit), refused=core.http_refused)
    config = uvicorn.Config(create_app(settings, orchestrator=core), log_config=None, http=guarded_protocol(limits),
                            log_level=settings.log_level.lower(),
                            access_log=settings.log_level == "DEBUG", lifespan="on",
                            timeout_graceful_shutdown=3,
                            ssl_certfile=settings.tls_cert or None, ssl_keyfile=settings.tls_key or None)
    try:
        config.load()  # with tls_cert: its certificate and key are loaded here
    except OSError as exc:  # ssl.SSLError is one
        sock.close()
        raise StartupError(f"cannot use the TLS certificate {settings.tls_cert} with the key {settings.tls_key} "
                           f"(tls_cert, tls_key): {exc.strerror or exc}") from None
    try:
        await core.start()
    except BaseException:
        sock.close()
        raise
    server = _Server(config)

    def on_signal(signum: int) -> None:
        log.info("event=signal signal=%s", signal.Signals(signum).name)
        core.closing.set()
        server.exit(force=server.should_exit)

    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, on_signal, signum)
    http_host, http_port = sock.getsockname()[:2]
    log.info("event=listening http=%s://%s:%d control=%s results=%s file_limit=%d max_connections=%d "
             "max_per_peer=%d request_timeout_s=%g", "https" if settings.tls_cert else "http", http_host, http_port,
             core.control_endpoint, core.results_endpoint, file_limit, limits.max_total, limits.max_per_peer,
             limits.request_timeout_s)
    try:
        await server.serve(sockets=[sock])
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(signum)
        await core.stop()
        sock.close()
    return 0 if server.started else 1

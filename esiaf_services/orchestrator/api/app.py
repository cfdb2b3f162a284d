"""The FastAPI application factory. Nothing is built at import: state lives in the lifespan."""
from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi_offline import FastAPIOffline  # /docs without a CDN: robots are often offline
from starlette.exceptions import HTTPException

from esiaf import auth

from ..core import Orchestrator
from ..settings import OrchestratorSettings
from . import components, dashboard, fused, fusions, health, latency, metrics, playback, results, streams, topics, ws
from .auth import TokenAuth
from .errors import with_allow_header
from .limits import BodyLimit
from .openapi import documented
from .voices import router as voices_router

DESCRIPTION = """\
Registers ESIAF components, heartbeats them over ZeroMQ, stores every result in SQLite,
fuses results and serves the fused results. The wire protocols are in docs/protocol.md.
"""


def create_app(settings: OrchestratorSettings, *,
               orchestrator: Orchestrator | None = None) -> FastAPI:
    """The orchestrator's HTTP app.

    Without ``orchestrator``, the app's lifespan starts one (binding its ZeroMQ
    sockets and opening its database) and stops it at shutdown; the command line
    starts its own first, so that a port in use is reported before serving.
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        core = orchestrator or Orchestrator(settings)
        if orchestrator is None:
            await core.start()
        app.state.core = core
        try:
            yield
        finally:
            if orchestrator is None:
                await core.stop()

    app = FastAPIOffline(title="ESIAF orchestrator", version="0.1.0", description=DESCRIPTION,
                         lifespan=lifespan)
    for module in (components, topics, streams, playback, results, latency, fused, ws, fusions, health, metrics,
                   dashboard):
        app.include_router(module.router)
    app.mount(dashboard.ASSETS_PREFIX, dashboard.assets(), name="dashboard")
    app.include_router(voices_router)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(TokenAuth, token=settings.token or auth.token(), allowed_origins=settings.allowed_origins)
    # Starlette types a handler as taking any Exception; this one is registered for HTTPException only
    app.add_exception_handler(HTTPException, with_allow_header)  # type: ignore[arg-type]
    # replacing app.openapi is FastAPI's documented way to extend the schema
    app.openapi = documented(app)  # type: ignore[method-assign]  # what the two middlewares answer
    return app

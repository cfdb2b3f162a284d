"""Command line: python -m esiaf_services.orchestrator [--config FILE] [--host H] [--port P]
[--db PATH] [--fresh | --recover]. Exit codes: 0 after SIGINT/SIGTERM, 2 for bad settings, a port
in use or a database that cannot be used (one line on stderr), 1 if the server failed otherwise."""
from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys

from esiaf.argparsing import OneLineParser
from esiaf.auth import TokenError, redact_logs
from esiaf.runner import limit_native_threads
from esiaf.services import known_services
from esiaf.settings import SettingsError, unknown_variables

from .connections import AcceptBackoffLoop
from .core import StartupError
from .server import serve
from .settings import load
from .store.recover import RecoveryError, recover

log = logging.getLogger("esiaf_services.orchestrator")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = OneLineParser(prog="python -m esiaf_services.orchestrator",
                                     description="ESIAF orchestrator")
    parser.add_argument("--config", help="YAML settings file (or ESIAF_ORCHESTRATOR_CONFIG)")
    parser.add_argument("--host", help="where to listen (HTTP, control and results sockets)")
    parser.add_argument("--port", type=int, help="HTTP port")
    parser.add_argument("--db", help="SQLite database file")
    start = parser.add_mutually_exclusive_group()
    start.add_argument("--fresh", action="store_true", help="delete the database first")
    start.add_argument("--recover", action="store_true",
                       help="if the database is corrupt, copy what can still be read into a new file, keep "
                            "the damaged one beside it (.corrupt-TIME) and start on the copy")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    limit_native_threads()  # the enrolment's speaker embeddings (api/voices.py) share the cores too
    args = parse_args(argv)
    try:
        settings = load(args.config, host=args.host, port=args.port, db_path=args.db)
    except SettingsError as exc:
        print(f"orchestrator: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=settings.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    redact_logs(settings.token)  # no token in its log (the dashboard's websocket URL carries one)
    for name in unknown_variables(os.environ, known_services()):
        log.warning("%s names no service and no common setting: ignored; a typo?", name)
    try:
        report: list[str] = []
        if args.recover:
            recovered = recover(settings.db_path)
            report = recovered.lines() if recovered else []
            for line in report:
                print(f"orchestrator: {line}", file=sys.stderr, flush=True)
        with asyncio.Runner(loop_factory=AcceptBackoffLoop) as runner:  # accept errors: connections.py
            return runner.run(serve(settings, fresh=args.fresh, recovered=report))
    except RecoveryError as exc:
        print(f"orchestrator: {exc}", file=sys.stderr)
        return 2
    except (StartupError, TokenError) as exc:
        print(f"orchestrator: {exc}", file=sys.stderr)
        return 2

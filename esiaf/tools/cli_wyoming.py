"""``esiaf wyoming``: the pipeline of ``esiaf run`` (orchestrator, recogniser, VAD, labellers) with the
wyoming service as its source instead of a grabber: a Wyoming speech-to-text server for Home
Assistant (docs/wyoming.md). It runs until Ctrl-C or SIGTERM, restarting a service that dies."""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import socket
import time

from esiaf.services import known_services
from esiaf.tools.cli_args import check_port_free, check_settings, parse_without
from esiaf.tools.cli_start import (
    prepare,
    start_orchestrator,
    start_services,
    wait_for_registration,
    wait_for_subscriptions,
)
from esiaf.tools.launcher import START_TIMEOUT_S, LaunchError, OrchestratorClient, Supervisor, wait_until
from esiaf.tools.terminal import err

WATCH_EVERY_S = 0.2  # how often the children are looked after


def listening(host: str, port: int) -> bool:
    """Whether something accepts TCP connections at ``host:port`` (0.0.0.0: on this host)."""
    try:
        with socket.create_connection(("127.0.0.1" if host in ("0.0.0.0", "::", "") else host, port), timeout=1.0):
            return True
    except OSError:
        return False


def wyoming_env(args: argparse.Namespace) -> dict[str, str]:
    """The wyoming service's settings from the command line: where it listens, what `describe` says."""
    grammar = "" if not args.grammar else "the RoboCup@Home questions" if args.grammar == "robocup" \
        else os.path.basename(args.grammar)
    model = args.asr or "pocketsphinx"
    return {"ESIAF_WYOMING_LISTEN_HOST": args.listen, "ESIAF_WYOMING_PORT": str(args.wyoming_port),
            "ESIAF_WYOMING_MODEL": model,
            "ESIAF_WYOMING_MODEL_DESCRIPTION": f"{model} with the grammar {grammar}" if grammar else model,
            "ESIAF_WYOMING_LANGUAGES": json.dumps(args.language or ["en"])}


def serve(args: argparse.Namespace) -> int:
    if importlib.util.find_spec("wyoming") is None:
        raise LaunchError("esiaf wyoming needs the wyoming package: pip install 'esiaf[wyoming]'")
    without = parse_without(args.without)
    check_settings(os.environ, known_services())
    check_port_free(args.host, args.port, in_use="another orchestrator running? use --http-port")
    check_port_free(args.listen, args.wyoming_port, "--listen", "another Wyoming server running? use --port")
    workdir, supervisor, client = prepare(args, {})
    try:
        start_orchestrator(args, supervisor, client, workdir)
        pipeline = start_services(args, supervisor, None, 1, without, {})
        wait_for_registration(client, supervisor, pipeline.services, {})
        wait_for_subscriptions(client, supervisor, pipeline, 0)
        supervisor.ready()  # the vad's spare starts now
        wyoming = supervisor.start("wyoming", env=wyoming_env(args))
        wait_until(lambda: listening(args.listen, args.wyoming_port), supervisor, "the Wyoming server to listen",
                   START_TIMEOUT_S, wyoming)
        err(f"esiaf: Wyoming server at tcp://{args.listen}:{args.wyoming_port} (Home Assistant: the Wyoming "
            f"Protocol integration, this host and port); orchestrator at {client.url}; logs in {workdir / 'logs'}")
        watch(supervisor, client)
    finally:
        client.close()
        supervisor.stop()
    return 0


def watch(supervisor: Supervisor, client: OrchestratorClient) -> None:
    """Until stopped: what the services refuse said on stderr, a service that died reported and restarted
    (a crash loop ends the run: LaunchError)."""
    while True:
        supervisor.keep_spares()
        for child, line in supervisor.refusals():
            err(f"esiaf: {child.name} {line} (its log: {child.log_path})")
        for child in supervisor.exited():
            if not child.reported:
                child.reported = True
                client.report_dead(child.process.pid)
            supervisor.restart_when_due(child)
        time.sleep(WATCH_EVERY_S)


__all__ = ["LaunchError", "serve"]

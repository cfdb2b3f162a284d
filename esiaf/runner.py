"""Entry point shared by every service: arguments, settings, logging, exit codes.

A service's ``__main__`` is one line: ``raise SystemExit(main(MyProcessor))``; it runs in a node
of its own (esiaf/node.py), with the guests its ``guests`` setting names (esiaf/hosting.py).
Bad settings, a failed setup or a refused registration end the process with
exit code 2 and one line on stderr naming what is wrong; no traceback.
"""
from __future__ import annotations

import argparse
import contextlib
import ctypes
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from esiaf.argparsing import OneLineParser
from esiaf.auth import TokenError, redact_logs, token
from esiaf.control import RegistrationError
from esiaf.hosting import hosting_node
from esiaf.processor import Processor, SetupError
from esiaf.services import known_services
from esiaf.settings import (
    STANDBY_ENV,
    ComponentSettings,
    SettingsError,
    load_settings,
    nest,
    parse_value,
    sections,
    unknown_variables,
)

_PR_SET_NAME = 15  # prctl(2)
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s [{service}] %(message)s"


def configure_logging(service: str, level: str) -> None:
    logging.basicConfig(level=level.upper(), format=LOG_FORMAT.format(service=service), force=True)
    redact_logs()  # no token in a log


def parse_set(values: Sequence[str]) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SettingsError(f"--set takes KEY=VALUE, not {item!r}")
        # as environment values: 3, [1, 2], ...; energy.db_min: a backend's own setting
        nest(key.strip().replace("-", "_"), parse_value(value), overrides)
    return overrides


def settings_help(model: type[ComponentSettings], service: str) -> str:
    """Every setting, common ones included, with its default and its environment variable."""
    common = set(ComponentSettings.model_fields)
    nested = sections(model)
    lines = ["settings (defaults < --config YAML < environment < --set / flags):"]
    for name, field in model.model_fields.items():
        if name in nested:
            continue
        default = field.get_default(call_default_factory=True)
        env = f"ESIAF_{service.upper()}_{name.upper()}" + (f" or ESIAF_{name.upper()}" if name in common else "")
        lines.append(f"  {name} = {default!r}  ({env})")
    for name, inner in nested.items():
        what = f"the {name} backend (only with backend {name})" if name in getattr(model, "backends", ()) else name
        lines.append(f"settings of {what}; --set {name}.KEY=VALUE:")
        for key, field in inner.model_fields.items():
            default = field.get_default(call_default_factory=True)
            lines.append(f"  {name}.{key} = {default!r}  (ESIAF_{service.upper()}_{name.upper()}__{key.upper()})")
    return "\n".join(lines)


# the variables that choose numpy's BLAS (and OpenMP) threads: set, they are the user's choice
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_native_threads() -> None:
    """One BLAS thread in this process, unless the user set one of THREAD_VARIABLES. The services
    share the robot's cores: a BLAS thread pool per process spins its idle threads against the
    other processes' work (measured on a loaded 2-core machine: one voiceid embedding cost 1.0 to
    2.5 CPU-s with OpenBLAS's default pool, 0.1 CPU-s with one thread)."""
    if any(name in os.environ for name in THREAD_VARIABLES):
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"  # for the BLAS libraries loaded from now on (scipy's own)
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api="blas")  # and those loaded already (numpy's)


SPARE_NAME = b"esiaf-spare"  # a waiting spare's process name (ps, top, psutil's name())


def standby() -> bool:
    """A spare's wait (esiaf/tools/launcher.py): True once its launcher writes a line on stdin, False at
    the end of stdin (the launcher ended). While it waits, its process name is SPARE_NAME."""
    name = Path("/proc/self/comm").read_bytes().strip() if Path("/proc/self/comm").is_file() else b"python"
    _set_process_name(SPARE_NAME)
    released = bool(sys.stdin.readline())
    _set_process_name(name)
    return released


def _set_process_name(name: bytes) -> None:
    with contextlib.suppress(OSError, AttributeError):  # Linux only: elsewhere the name stays
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_NAME, ctypes.c_char_p(name[:15]), 0, 0, 0)


def main(component_cls: type[Processor], argv: Sequence[str] | None = None) -> int:
    limit_native_threads()
    service = component_cls.service
    doc_lines = (component_cls.__doc__ or "").strip().splitlines()
    parser = OneLineParser(prog=f"python -m esiaf_services.{service}",
                                     description=doc_lines[0] if doc_lines else f"the {service} component",
                                     epilog=settings_help(component_cls.Settings, service),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help=f"YAML settings file (also ESIAF_{service.upper()}_CONFIG)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one setting (repeatable; the value is read as YAML, e.g. 3 or [1, 2])")
    for name, help_text in component_cls.options.items():
        flag = "--" + name.replace("_", "-")
        if component_cls.Settings.model_fields[name].annotation is bool:
            parser.add_argument(flag, dest=name, action="store_true", default=None, help=help_text)
        else:
            parser.add_argument(flag, dest=name, help=help_text)
    args = parser.parse_args(argv)
    try:
        overrides = parse_set(args.set)
        cli = {name: getattr(args, name) for name in component_cls.options}
        settings = load_settings(component_cls.Settings, service, config=args.config,
                                 **{**overrides, **cli})
        token()  # a token file that cannot be read: said now, not at the first request
    except (SettingsError, TokenError) as exc:
        return refuse_start(service, exc)
    configure_logging(service, settings.log_level)
    services = known_services() | {service}
    for name in unknown_variables(os.environ, services):
        logging.getLogger(service).warning(
            "%s names no service (%s) and no common setting: ignored; a typo? (a plug-in folder's own "
            "settings are not known here)", name, ", ".join(sorted(services)))
    if os.environ.get(STANDBY_ENV) == "1" and not standby():
        return 0  # a spare (esiaf/tools/launcher.py) whose launcher ended without needing it
    try:
        return hosting_node(component_cls(settings)).run()
    except (SetupError, RegistrationError) as exc:
        return refuse_start(service, exc)
    except KeyboardInterrupt:
        return 130


def refuse_start(service: str, problem: object) -> int:
    """A service that cannot start: one line on stderr (before logging is set up; after, stderr is its
    log too), naming the service and what is wrong, and exit code 2."""
    print(f"{service}: {problem}", file=sys.stderr)
    return 2

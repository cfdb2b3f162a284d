"""The ``esiaf`` command: ``esiaf run`` starts the whole pipeline as local processes.

    esiaf run --input FILE|FOLDER|SESSION.mcap [--input ...] [--array SPEC] [--fast] [--grammar FILE|robocup]
              [--serve] [--record FILE.mcap] [--diff]
              [--without emotion,...] [--replicas asr=2 ...]
    esiaf run --mic DEVICE [--array SPEC]
    esiaf eval robocup [--runs N] [--seed S] [--snr LO:HI] [--array SPEC] [-- RUN OPTIONS]
    esiaf keys DIR [--component NAME ...]      (CURVE key pairs: esiaf/keys.py)
    esiaf wyoming [--port 10300] [--listen ADDR] [--grammar FILE|robocup] [--asr ...]   (docs/wyoming.md)
    esiaf record --out FILE.mcap [--url URL]   (a running pipeline to MCAP: esiaf/tools/mcap_record.py)
    esiaf mcap diff RECORDED.mcap REPLAYED.mcap (esiaf/tools/mcap_diff.py)

It starts the orchestrator, the recogniser (pocketsphinx and voiceid hearing the VAD's utterances
through the denoiser, ``--denoiser``), the VAD, the emotion, gender and voiceid services (on the VAD's output) and
the grabber (with a microphone array also the ssl service and the beamformer, the VAD hearing the
array steered at the talker; with ``--no-beamformer`` the channel splitter instead, the VAD hearing
the first microphone), prints each fused result as one line as
it arrives, and with ``--input`` exits once the file has been played and its last fused result
printed. Several ``--input`` (or a folder) are played at once, each by a grabber of its own as a
stream of its own; the run ends once every stream has ended. With ``--serve`` it never ends on its
own: Ctrl-C or SIGTERM stops it. ``--replicas asr=2`` runs two recognisers that share the streams.
``--without`` leaves analysers out; the orchestrator's default fusion waits only for the analysers
that are running.
"""
from __future__ import annotations

import importlib
import logging
import signal
import sys
from collections.abc import Sequence
from typing import Any

from esiaf.tools.cli_args import check_values, parse_args
from esiaf.tools.errors import LaunchError
from esiaf.tools.terminal import err

# the run command's parts, importable from here as before; imported on first use (PEP 562), so that a
# bad value is answered before the pipeline's modules are loaded
_EXPORTS = {
    **dict.fromkeys(["ANALYSERS", "check_array", "check_input", "check_port_free", "parse_channels",
                     "parse_without"], "esiaf.tools.cli_args"),
    **dict.fromkeys(["DRAIN_TIMEOUT_S", "LABELS", "LONG_FILE_S", "PROGRESS_EVERY_S", "follow", "format_line",
                     "report_health", "show_progress"], "esiaf.tools.cli_follow"),
    **dict.fromkeys(["array_env", "fuse_kinds", "run", "shown_path", "topic_ready"], "esiaf.tools.cli_start"),
    "START_TIMEOUT_S": "esiaf.tools.launcher",
}
__all__ = sorted([*_EXPORTS, "LaunchError", "main", "parse_args"])


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class Terminated(Exception):
    """SIGTERM came: stop every service and end the run, as asked (exit code 0)."""


def _terminate(signum: int, frame: object) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not cut the services' shutdown short
    raise Terminated


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["eval"]:
        from esiaf.tools.evaluation import main as evaluate
        return evaluate(argv[1:])
    if argv[:1] == ["record"]:
        from esiaf.tools.mcap_record import main as record
        return record(argv[1:])
    if argv[:1] == ["mcap"]:
        from esiaf.tools.mcap_diff import main as mcap
        return mcap(argv[1:])
    if argv[:1] == ["keys"]:
        from esiaf.keys import main as make_keys
        return make_keys(argv[1:])
    args = parse_args(argv)
    try:
        check_values(args)
    except LaunchError as exc:
        err(f"esiaf: {exc}")
        return 2
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    signal.signal(signal.SIGTERM, _terminate)  # like Ctrl-C, the services are stopped on the way out
    from esiaf.tools.cli_start import run
    try:
        if args.command == "wyoming":
            from esiaf.tools.cli_wyoming import serve
            return serve(args)
        return run(args)
    except Terminated:
        err("esiaf: stopped (SIGTERM)")
        return 0
    except LaunchError as exc:
        err(f"esiaf: {exc}")
        return 2
    except KeyboardInterrupt:
        err("esiaf: stopped")
        return 130


if __name__ == "__main__":
    raise SystemExit(main())

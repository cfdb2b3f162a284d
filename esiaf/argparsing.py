"""The command lines' parser: ``esiaf run``, the orchestrator and every service answer a bad option
with one line and exit code 2."""
from __future__ import annotations

import argparse
from typing import NoReturn


class OneLineParser(argparse.ArgumentParser):
    """argparse, whose errors are one line (``esiaf run: argument --port: ...``) and exit code 2,
    without the usage text above them (``--help`` shows it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")

"""ruff and mypy pass on the repository, with the configs in pyproject.toml: CI runs them here.

Both come with the test extra (./setup.sh), next to the interpreter that runs the tests. They
write no cache into the checkout. The last test shows that each does fail on a bad file with
these configs, so a pass above means something.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from esiaf.tools.testing import REPO

BIN = Path(sys.executable).parent  # the virtual environment's bin (not resolved: that would leave it)
CONFIG = REPO / "pyproject.toml"


def run_tool(name: str, *args: str) -> subprocess.CompletedProcess:
    tool = BIN / name
    if not tool.exists():
        pytest.fail(f"{tool} is missing: the test extra installs it (./setup.sh)")
    return subprocess.run([str(tool), *args], cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def ruff(*args: str) -> subprocess.CompletedProcess:
    return run_tool("ruff", "check", "--no-cache", "--config", str(CONFIG), *args)


def mypy(cache: Path, *args: str) -> subprocess.CompletedProcess:
    return run_tool("mypy", "--config-file", str(CONFIG), "--cache-dir", str(cache), *args)


def test_ruff_finds_nothing():
    done = ruff(".")
    assert done.returncode == 0, f"ruff check found problems:\n{done.stdout}{done.stderr}"


def test_mypy_finds_nothing(tmp_path):
    done = mypy(tmp_path)  # the files pyproject.toml names
    assert done.returncode == 0, f"mypy found problems:\n{done.stdout}{done.stderr}"


def test_both_fail_on_a_bad_file(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n\n\ndef twice(n: int) -> int:\n    return n * 2\n\n\ntwice('a')\n")
    linted = ruff(str(bad))
    assert linted.returncode == 1 and "F401" in linted.stdout, linted.stdout + linted.stderr
    typed = mypy(tmp_path / "cache", str(bad))
    assert typed.returncode == 1 and "[arg-type]" in typed.stdout, typed.stdout + typed.stderr


def cross_service_imports() -> set[tuple[str, str]]:
    """(service, module) for every import of another service's module by a service's own code
    (its tests, which may run services together, aside)."""
    import ast
    root = REPO / "esiaf_services"
    found = set()
    for path in root.rglob("*.py"):
        relative = path.relative_to(root)
        if "tests" in relative.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules = [node.module]
            else:
                continue
            for module in modules:
                parts = module.split(".")
                if parts[0] == "esiaf_services" and len(parts) > 1 and parts[1] != relative.parts[0]:
                    found.add((relative.parts[0], module))
    return found


def test_services_build_on_the_sdk_not_on_each_other():
    found = cross_service_imports()
    assert found == set(), "a service imports another service's code: move what they share into the " \
        "SDK (esiaf/); a repository tool that spans services goes beside bench/ (training/)"

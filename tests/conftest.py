"""Fixtures of the container tests (tests/test_containers*.py): the offline image build, once per
session, and compose projects of their own, downed at the end."""
from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
from container_kit import BUILD_TIMEOUT_S, EXAMPLE, Project, run

from esiaf.tools.testing import REPO


@pytest.fixture(scope="session")
def docker_images():
    """Builds every image offline (once per session); skips when no Docker engine answers."""
    if not shutil.which("docker"):
        pytest.skip("docker is not installed")
    if run("docker", "info", check=False, timeout=60).returncode != 0:
        pytest.skip("the Docker engine does not answer (docker info failed)")
    started = time.monotonic()
    result = run("bash", str(REPO / "scripts" / "build_images.sh"), timeout=BUILD_TIMEOUT_S, check=False)
    print(result.stderr, end="")
    assert result.returncode == 0, result.stderr[-3000:]
    print(f"offline image build: {time.monotonic() - started:.0f} s")
    return result.stderr



@pytest.fixture
def project(docker_images, tmp_path):
    projects: list[Project] = []

    def make(wav: Path = EXAMPLE) -> Project:
        projects.append(Project(tmp_path / f"p{len(projects)}", wav))
        return projects[-1]

    yield make
    for p in projects:
        p("down", "-v", "--remove-orphans", "-t", "5", check=False)


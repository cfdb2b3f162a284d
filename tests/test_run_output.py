"""What ``esiaf run`` prints and where: a stream id that URLs must encode, one played before in the
workdir, a label with terminal escapes, a standard output that cannot be written. Every service as a
process, real audio, the workdir's real database."""
from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from esiaf.tools.testing import REPO, free_port

pytestmark = pytest.mark.e2e

WAV = REPO / "examples" / "robocup_questions.wav"
STREAM = "kitchen robot#1&fusion=x"  # a space, a fragment and a query separator: each must be encoded
FORGED = "\x1b[2K\rforged"  # clears the line, goes back to its start, writes its own
EVIL_LABEL = f'''\
from esiaf import UtteranceComponent, main

class Forger(UtteranceComponent):
    """Labels every utterance with a name that would rewrite the terminal."""
    service = "forger"
    kind = "forger"

    def analyse(self, samples, rate):
        return {{"label": {FORGED!r}, "probability": 1.0}}

raise SystemExit(main(Forger))
'''


def esiaf_run(workdir: Path, stream_id: str, plugin: Path, stdout) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf", "run", "--input", str(WAV), "--fast", "--without",
                           "emotion,gender,voiceid", "--with", str(plugin), "--stream-id", stream_id,
                           "--port", str(free_port()), "--workdir", str(workdir)],
                          cwd=REPO, stdout=stdout, stderr=subprocess.PIPE, text=True, timeout=300)


def stored(workdir: Path, stream_id: str) -> dict[str, int]:
    """What the workdir's database holds of the stream: fused revisions (each printed as a line of its
    own), fused results, the vad's segments and the recogniser's results."""
    with sqlite3.connect(workdir / "esiaf.db") as db:
        revisions, fused = db.execute("SELECT COUNT(*), COUNT(DISTINCT id) FROM fused WHERE stream_id = ?",
                                      (stream_id,)).fetchone()
        kinds = dict(db.execute("SELECT type, COUNT(*) FROM results WHERE stream_id = ? GROUP BY type",
                                (stream_id,)).fetchall())
    return {"revisions": revisions, "fused": fused, "vad": kinds.get("vad", 0), "speech": kinds.get("speech", 0)}


def test_names_are_encoded_escaped_a_reused_stream_refused_and_a_full_stdout_stops_nothing(tmp_path):
    plugin = tmp_path / "forger"
    plugin.mkdir()
    (plugin / "__main__.py").write_text(EVIL_LABEL)
    workdir = tmp_path / "work"

    first = esiaf_run(workdir, STREAM, plugin, subprocess.PIPE)
    assert first.returncode == 0, first.stderr
    lines = first.stdout.splitlines()
    first_run = stored(workdir, STREAM)
    assert first_run["fused"] and len(lines) == first_run["revisions"], first_run  # every fused result printed
    # the label is on each line, its escapes shown, not obeyed
    assert all("forger \\x1b[2K\\rforged (1.00)" in line for line in lines), lines
    assert "\x1b" not in first.stdout and "\r" not in first.stdout

    again = esiaf_run(workdir, STREAM, plugin, subprocess.PIPE)
    assert again.returncode == 2 and again.stdout == ""
    assert again.stderr.strip().splitlines() == [
        f"esiaf: stream {STREAM} was played before in {workdir}: give another --stream-id, or another --workdir"]

    with open("/dev/full", "w") as full:  # a disk that is full under standard output
        third = esiaf_run(workdir, "second run", plugin, full)
    assert third.returncode == 0, third.stderr
    assert "esiaf: standard output cannot be written (No space left on device)" in third.stderr
    assert "Traceback" not in third.stderr
    # the services went on to the end of the file: every segment recognised, every recognised one fused
    third_run = stored(workdir, "second run")
    assert third_run["vad"] == first_run["vad"] > 0, (first_run, third_run)
    assert third_run["fused"] == third_run["speech"] == third_run["vad"], (first_run, third_run)

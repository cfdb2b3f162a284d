"""The analyser docs/writing-an-analyser.md walks through is examples/analysers/loudness, and it
works: run as its own process (``python examples/analysers/loudness``) against the real orchestrator,
over real ZeroMQ sockets, its result reaches /results with the utterance's span."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from esiaf import AudioFormat, Component
from esiaf.tools.testing import REPO, poll

EXAMPLE = REPO / "examples" / "analysers" / "loudness"


def doc_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (REPO / "docs" / "writing-an-analyser.md").read_text(), re.S)


def test_the_doc_shows_the_example_as_it_is():
    blocks = doc_blocks()
    assert (EXAMPLE / "loudness.py").read_text() in blocks
    assert (EXAMPLE / "__main__.py").read_text() in blocks


class SpeechSource(Component):
    """Stands in for the VAD: one utterance on vad/speech."""
    service = "vad"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("vad/speech", AudioFormat(16000, "int16"))

    def produce(self):
        assert self.wait_for_subscribers("vad/speech", 1, timeout_s=30)
        loud = np.full(16000, 16384, dtype=np.int16)  # a second at half of full scale: 90 dB
        self.publish("vad/speech", np.zeros(320, dtype=np.int16), 1_000, 20_001_000)
        self.publish("vad/speech", loud, 20_001_000, 1_020_001_000, segmentation_ended=True,
                     segment=(20_001_000, 1_020_001_000))
        while not self.stopping:
            self.sleep_until(time.monotonic() + 0.1)


def test_the_example_analyser_in_the_pipeline(orchestrator):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    process = subprocess.Popen([sys.executable, str(EXAMPLE)], env=env, stderr=subprocess.PIPE, text=True)
    try:
        poll(lambda: orchestrator.component("loudness"), timeout_s=30)
        source = SpeechSource(SpeechSource.Settings(name="vad", orchestrator_url=orchestrator.url))
        thread = threading.Thread(target=source.run, daemon=True)
        thread.start()
        results = poll(lambda: orchestrator.http.get("/results", params={"component": "loudness"}).json()["items"],
                       timeout_s=30)
        assert results[0]["span"] == {"start_ns": 20_001_000, "end_ns": 1_020_001_000}
        assert results[0]["type"] == "loudness"
        assert results[0]["loudness"]["value"] == pytest.approx(96.0 - 6.02, abs=0.01)
        assert results[0]["loudness"]["attributes"]["rms_db"] == pytest.approx(96.0 - 6.02, abs=0.01)  # a constant
        source.stop()
        thread.join(timeout=10)
    finally:
        process.terminate()
        assert process.wait(timeout=10) == 0, process.stderr.read()

"""The component that README.md shows as "Writing a component" really works."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading

import numpy as np
import pytest

from esiaf import AudioFormat, Component
from esiaf.tools.testing import REPO, poll


def readme_component() -> str:
    text = (REPO / "README.md").read_text()
    return re.search(r"```python\n(# my_analysers/loudness/__main__\.py.*?)```", text, re.S).group(1)


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
            self._service(100)


def test_the_readme_component(orchestrator, tmp_path):
    path = tmp_path / "loudness_component.py"
    path.write_text(readme_component())
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": orchestrator.url}
    process = subprocess.Popen([sys.executable, str(path)], env=env, stderr=subprocess.PIPE, text=True)
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
        source.stop()
        thread.join(timeout=10)
    finally:
        process.terminate()
        assert process.wait(timeout=10) == 0, process.stderr.read()

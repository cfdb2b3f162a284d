"""The example analysers (examples/analysers/) in-process with esiaf.testing.run_analyser: the code
docs/writing-an-analyser.md shows, known answers on synthetic audio, and what the runner promises
(per VAD-cut utterance or per span, "nothing" for what is too short, the two-argument form)."""
from __future__ import annotations

import math
import re
import sys

import numpy as np
import pytest

from esiaf import UtteranceComponent
from esiaf.testing import run_analyser
from esiaf.tools.testing import REPO

EXAMPLE = REPO / "examples" / "analysers" / "loudness"
QUESTIONS = REPO / "examples" / "robocup_questions.wav"


@pytest.fixture(autouse=True)
def example_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))  # as ``python examples/analysers/loudness`` has it
    monkeypatch.chdir(REPO)
    yield
    sys.modules.pop("loudness", None)


def test_the_doc_s_test_runs():
    text = (REPO / "docs" / "writing-an-analyser.md").read_text()
    [block] = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "run_analyser" in b]
    exec(compile(block, "docs/writing-an-analyser.md", "exec"), {})


def tone(seconds: float, amplitude: float, rate: int = 16000) -> np.ndarray:
    t = np.arange(int(seconds * rate)) / rate
    return (amplitude * np.sin(2 * np.pi * 440 * t)).astype(np.float32)


def test_known_levels_of_a_tone_per_span():
    from loudness import Loudness
    audio = np.concatenate([np.zeros(8000, np.float32), tone(1.0, 0.5), np.zeros(8000, np.float32)])
    [found] = run_analyser(Loudness, (audio, 16000), spans=[(0.5, 1.5)], stream_id="tone")
    assert (found.kind, found.stream_id, found.start_s, found.end_s) == ("loudness", "tone", 0.5, 1.5)
    assert found.payload["value"] == pytest.approx(96 + 20 * math.log10(0.5), abs=0.01)  # half scale: 89.98 dB
    assert found.payload["attributes"]["rms_db"] == pytest.approx(96 + 20 * math.log10(0.5 / math.sqrt(2)),
                                                                  abs=0.05)
    assert found.payload["attributes"]["duration_s"] == 1.0


def test_one_result_per_utterance_the_vad_cuts_at_the_truth_s_times():
    import json

    from loudness import Loudness
    truth = json.loads(QUESTIONS.with_suffix(".json").read_text())["sentences"]
    for vad in ("energy", "silero"):
        results = run_analyser(Loudness, QUESTIONS, vad=vad)
        assert len(results) == len(truth), vad
        for found, said in zip(results, truth, strict=True):
            assert found.start_s < said["end_s"] and found.end_s > said["start_s"], (vad, found, said)
            assert 80 < found.payload["value"] < 96


def test_the_sdk_says_nothing_for_too_short_and_too_quiet():
    from loudness import Loudness
    audio = np.concatenate([tone(1.0, 0.5), tone(1.0, 0.001)])
    short, quiet = run_analyser(Loudness, (audio, 16000), spans=[(0.0, 0.2), (1.0, 2.0)])
    assert short.nothing.startswith("too short") and short.payload == {}
    assert quiet.nothing.startswith("silence")


def test_settings_and_a_48_khz_file_converted_to_the_declared_rate():
    from loudness import Loudness
    results = run_analyser(Loudness, (tone(1.0, 0.5, 48000), 48000), spans=[(0.0, 1.0)], window_ms=500)
    assert results[0].payload["value"] == pytest.approx(89.98, abs=0.05)


class Duration(UtteranceComponent):
    service = "duration"
    kind = "duration"

    def analyse(self, samples, rate):  # the form of earlier releases
        return {"value": len(samples) / rate, "attributes": {"stream": self.utterance_stream_id}}


def test_the_two_argument_form_still_works(caplog):
    [found] = run_analyser(Duration, (tone(1.0, 0.5), 16000), spans=[(0.25, 1.0)], stream_id="old")
    assert found.payload["value"] == 0.75 and found.payload["attributes"]["stream"] == "old"
    assert "analyse(samples, rate) is deprecated" in caplog.text


class Broken(UtteranceComponent):
    service = "broken"
    kind = "broken"

    def analyse(self, utterance):
        raise ZeroDivisionError("a bug")


def test_an_analyser_s_exception_reaches_the_test():
    with pytest.raises(ZeroDivisionError, match="a bug"):
        run_analyser(Broken, (tone(1.0, 0.5), 16000), spans=[(0.0, 1.0)])

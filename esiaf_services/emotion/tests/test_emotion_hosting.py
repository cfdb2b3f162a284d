"""Gender as a guest in the emotion service's process: the same results as two processes, with each
utterance's features computed once (real processes, sockets and models, EmoDB speech)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile

from esiaf.component import SetupError
from esiaf.hosting import guest_class
from esiaf.speech.classifiers import load_backend
from esiaf.speech.opensmile import FeatureExtractor
from esiaf.tools.testing import REPO, poll, shared_data
from esiaf_services.emotion.service import MODELS
from esiaf_services.emotion.tools.pipeline import EmotionPipeline, build_recording
from esiaf_services.gender.service import MODELS as GENDER_MODELS
from esiaf_services.gender.service import Gender

pytestmark = pytest.mark.e2e
FEATURES = "ComParE_2016@16000"  # what both bundled models classify


def test_classifiers_in_one_process_share_one_extractor_and_its_answers():
    samples, _ = soundfile.read(shared_data("emodb/wav/03a01Fa.wav"), dtype="float32")
    emotion, gender = (load_backend("onnx", "emotion4", models_dir=MODELS),
                       load_backend("onnx", "gender", models_dir=GENDER_MODELS))
    assert emotion.features is gender.features  # type: ignore[attr-defined]
    shared = emotion.features  # type: ignore[attr-defined]
    before = shared.counts()
    got = emotion.classify(samples), gender.classify(samples.copy())  # equal samples, another array
    assert shared.counts() == {"computed": before["computed"] + 1, "reused": before["reused"] + 1}
    fresh = FeatureExtractor("ComParE_2016")(samples)  # what each computed on its own before
    assert np.array_equal(shared(samples), fresh)
    assert got == (dict(zip(emotion.labels, emotion._run(fresh).tolist(), strict=True)),  # type: ignore[attr-defined]
                   dict(zip(gender.labels, gender._run(fresh).tolist(), strict=True)))  # type: ignore[attr-defined]
    with pytest.raises(ValueError):
        shared(samples)[0] = 1.0  # one vector for every classifier: none may change it


def play(tmp_path: Path, files: list[Path], hosted: bool) -> tuple[dict, dict]:
    """Each fused result's (kind, span from the stream's start) -> its label and probabilities, and
    each service's registration, once both have reported every utterance they analysed."""
    workdir = tmp_path / ("hosted" if hosted else "apart")
    workdir.mkdir()
    build_recording(files, workdir / "utterances.wav", 1.2)
    pipeline = EmotionPipeline(workdir, "emotion4", "gender", "s", hosted=hosted)
    try:
        arrived, origin_ns = pipeline.play(workdir / "utterances.wav", fast=True, timeout_s=150)
        results = {}
        for _, fused in arrived:
            kind, anchor = fused["fusion"], fused["anchor"]
            span = (anchor["span"]["start_ns"] - origin_ns, anchor["span"]["end_ns"] - origin_ns)
            results[kind, span] = anchor[kind]
        counted = sum(1 for (kind, _), result in results.items() if kind == "emotion" and (result or {}).get("label"))

        def reported() -> dict | None:
            components = {c["name"]: c for c in pipeline.client.components() if c["status"] == "alive"}
            infos = [components.get(name, {}).get("stats", {}).get("info", {}) for name in ("emotion", "gender")]
            done = all(info.get("analysed") == counted for info in infos)
            return components if done else None
        components = poll(reported, timeout_s=10)
    finally:
        pipeline.close()
    return results, components


def test_a_guest_gives_the_same_results_as_its_own_process_and_the_features_are_computed_once(tmp_path):
    files = [shared_data(f"emodb/wav/{name}.wav") for name in
             ("03a01Fa", "03a04Nc", "03b09Wa", "08a02Ab", "08b03Tc", "08b02Nb")]
    apart, alone = play(tmp_path, files, hosted=False)
    hosted, together = play(tmp_path, files, hosted=True)

    spans = {kind: {span for k, span in apart if k == kind} for kind in ("emotion", "gender")}
    assert spans["emotion"] == spans["gender"] and len(spans["emotion"]) >= len(files), sorted(apart)
    analysed = sum(1 for (kind, _), result in apart.items() if kind == "emotion" and (result or {}).get("label"))
    assert analysed >= len(files), apart  # each utterance judged (some cut in two by the VAD)
    assert hosted == apart  # the same labels and probabilities, to the last bit, over the same spans

    # apart: two processes, each computing the features of every utterance itself
    assert alone["emotion"]["pid"] != alone["gender"]["pid"]
    for name in ("emotion", "gender"):
        assert alone[name]["stats"]["info"]["features"] == {FEATURES: {"computed": analysed, "reused": 0}}
    # hosted: one process, two services; the features of each utterance computed once, and reused once
    assert together["emotion"]["pid"] == together["gender"]["pid"]
    assert together["emotion"]["stats"]["info"]["guests"] == ["gender"]
    assert together["gender"]["kind"] == "gender" and together["gender"]["component_id"].startswith("gender")
    assert together["gender"]["stats"]["info"]["model"] == "gender"
    for name in ("emotion", "gender"):
        assert together[name]["stats"]["info"]["features"] == {FEATURES: {"computed": analysed, "reused": analysed}}


def test_a_dead_host_is_reported_dead_with_its_guest(tmp_path):
    """esiaf run reports a process that died by its pid: the host and its guest are both dead at once,
    not only once silent for dead_after_s, so nothing waits for the guest's results meanwhile."""
    pipeline = EmotionPipeline(tmp_path, "emotion4", "gender", "s", hosted=True)
    try:
        host = next(child for child in pipeline.supervisor.children if child.name == "emotion")
        ids = {c["name"]: c["component_id"] for c in pipeline.client.components() if c["status"] == "alive"}
        host.process.send_signal(signal.SIGKILL)
        host.process.wait()
        reported = pipeline.client.report_dead(host.process.pid)
        assert reported is not None and set(reported.split(", ")) == {ids["emotion"], ids["gender"]}
        alive = {c["name"] for c in pipeline.client.components() if c["status"] == "alive"}
        assert not alive & {"emotion", "gender"}, alive
    finally:
        pipeline.close()


def test_a_guest_is_named_by_its_service_or_its_class():
    assert guest_class("gender") is Gender
    assert guest_class("esiaf_services.gender.service:Gender") is Gender
    for spec, message in (("nope", "cannot import esiaf_services.nope.service"),
                          ("esiaf_services.gender.service:Nope", "has no component Nope"),
                          ("esiaf.speech.opensmile:FeatureExtractor", "a subclass of Component")):
        with pytest.raises(SetupError, match=message):
            guest_class(spec)


def test_a_guest_that_cannot_be_loaded_stops_its_host_at_start_up_with_one_line(tmp_path):
    result = subprocess.run([sys.executable, "-m", "esiaf_services.emotion", "--set", "guests=[gender]"], cwd=REPO,
                            env={**os.environ, "ESIAF_GENDER_MODEL": str(tmp_path / "missing.onnx"),
                                 "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9"},
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines()[-1] == \
        f"emotion: gender model: model file {tmp_path / 'missing.onnx'} does not exist", result.stderr

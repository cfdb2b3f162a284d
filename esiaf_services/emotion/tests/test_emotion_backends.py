"""Backends: the ONNX one with a tiny hand-built model, the Python one with a toy class, and
every way a model can be unusable giving one clear line."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import soundfile

from esiaf.speech.classifiers import BackendError, OnnxClassifier, load_backend
from esiaf.speech.opensmile import FeatureExtractor, speech_span, without_digital_silence
from esiaf.tools.testing import REPO, shared_data

DATA = REPO / "esiaf_services" / "emotion" / "tests" / "data"
TOY = "esiaf_services.emotion.tests.toy_backend:LoudnessClassifier"


def tone(amplitude: float, seconds: float = 1.0, rate: int = 16000) -> np.ndarray:
    t = np.arange(int(seconds * rate)) / rate
    return (amplitude * np.sin(2 * np.pi * 220 * t) * (1 + 0.3 * np.sin(2 * np.pi * 3 * t))).astype(np.float32)


def test_onnx_backend_runs_the_model_on_the_label_maps_features():
    classifier = load_backend("onnx", str(DATA / "tiny.onnx"))
    card = json.loads((DATA / "tiny.json").read_text())
    assert classifier.labels == ("quiet", "loud")
    for amplitude in (0.001, 0.5):
        samples = tone(amplitude)
        # the backend leaves out the exact zeros at the ends (the tone's first sample)
        loudness = FeatureExtractor("eGeMAPSv02")(without_digital_silence(samples))[card["loudness_index"]]
        expected_loud = 1 / (1 + np.exp(-card["gain"] * (loudness - card["threshold"])))
        probabilities = classifier.classify(samples)
        assert probabilities["loud"] == pytest.approx(expected_loud, abs=1e-4)
        assert sum(probabilities.values()) == pytest.approx(1.0, abs=1e-5)
    assert classifier.classify(tone(0.5))["loud"] > 0.9 > 0.1 > classifier.classify(tone(0.001))["loud"]


def test_python_backend_builds_the_configured_class_with_its_options():
    classifier = load_backend("python", TOY, {"threshold_rms": 0.01})
    assert classifier.labels == ("quiet", "loud")
    assert classifier.classify(tone(0.1))["loud"] == pytest.approx(0.9)
    assert classifier.classify(tone(0.001))["quiet"] == pytest.approx(1.0)


@pytest.mark.parametrize("backend, model, options, message", [
    ("onnx", "no/such/model.onnx", {}, "model file no/such/model.onnx does not exist"),
    ("tflite", "emotion4", {}, "unknown backend 'tflite'; known: onnx, python"),
    ("python", "esiaf_services.emotion.tests.toy_backend", {}, "is 'package.module:ClassName'"),
    ("python", "esiaf_services.emotion.tests.toy_backend:Nope", {}, "cannot import the classifier"),
    ("python", "numpy:ndarray", {}, "is not a subclass of esiaf.speech.classifiers.Classifier"),
    ("python", TOY, {"bogus": 1}, "failed: TypeError"),
])
def test_unusable_backends_are_refused_with_a_clear_message(backend, model, options, message):
    with pytest.raises(BackendError, match=message.replace("(", r"\(").replace(".", r"\.")):
        load_backend(backend, model, options)


def copy_model(tmp_path, onnx_bytes: bytes | None = None, card: dict | None = None):
    path = tmp_path / "model.onnx"
    path.write_bytes(onnx_bytes if onnx_bytes is not None else (DATA / "tiny.onnx").read_bytes())
    (tmp_path / "model.json").write_text(json.dumps(card) if card is not None else (DATA / "tiny.json").read_text())
    return path


def test_corrupt_model_file(tmp_path):
    model = copy_model(tmp_path, onnx_bytes=(DATA / "tiny.onnx").read_bytes()[:300])
    with pytest.raises(BackendError, match=f"model file {model} is not a usable ONNX model"):
        OnnxClassifier(str(model))


def test_label_map_that_does_not_fit_the_model(tmp_path):
    model = copy_model(tmp_path, card={"labels": ["a", "b", "c"], "features": "eGeMAPSv02"})
    with pytest.raises(BackendError, match=r"gives 2 probabilities but its label map .* names 3 labels"):
        OnnxClassifier(str(model))
    copy_model(tmp_path, card={"labels": ["a", "b"], "features": "ComParE_2016"})
    with pytest.raises(BackendError, match="takes 88 features but ComParE_2016 has 6373"):
        OnnxClassifier(str(model))
    copy_model(tmp_path, card={"labels": ["a", "b"], "features": "MFCC"})
    with pytest.raises(BackendError, match="unknown feature set 'MFCC'"):
        OnnxClassifier(str(model))
    (tmp_path / "model.json").write_text("{not json")
    with pytest.raises(BackendError, match="is not JSON with 'labels' and 'features'"):
        OnnxClassifier(str(model))
    (tmp_path / "model.json").unlink()
    with pytest.raises(BackendError, match="cannot read the label map"):
        OnnxClassifier(str(model))


@pytest.mark.parametrize("service", ["emotion", "gender"])
def test_service_with_a_corrupt_model_exits_2_with_one_line(tmp_path, service):
    model = copy_model(tmp_path, onnx_bytes=b"this is not an onnx file")
    done = subprocess.run([sys.executable, "-m", f"esiaf_services.{service}", "--model", str(model)], cwd=REPO,
                          capture_output=True, text=True, timeout=120,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO),
                               "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9"})
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith(
        f"{service}: {service} model: model file {model} is not a usable ONNX model: ")
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("task", ["emotion4", "gender"])
def test_holdout_models_reproduce_the_training_scripts_predictions(task):
    """The service's feature code + ONNX give what scikit-learn gave at training time."""
    card = json.loads((REPO / "esiaf_services/emotion/models/holdout" / f"{task}.json").read_text())
    classifier = load_backend("onnx", str(REPO / "esiaf_services/emotion/models/holdout" / f"{task}.onnx"))
    for path, expected in list(card["predictions"].items())[:6]:
        samples, rate = soundfile.read(shared_data(f"emodb/{path}"), dtype="float32")
        first, end = speech_span(samples, rate)
        probabilities = classifier.classify(samples[first:end])
        assert max(probabilities, key=probabilities.get) == expected["predicted"], path


def test_digital_silence_around_an_utterance_does_not_change_its_label():
    """Zeros padded around a held-out utterance (a file's padding, a muted input) are left out: the
    probabilities are the utterance's own. Without that, 85 ms of zeros turned "neutral" at 0.99
    into "happy" for this one."""
    classifier = load_backend("onnx", str(REPO / "esiaf_services/emotion/models/holdout/emotion4.onnx"))
    samples, rate = soundfile.read(shared_data("emodb/wav/03b10Nc.wav"), dtype="float32")
    first, end = speech_span(samples, rate)
    speech = samples[first:end]
    padded = np.concatenate([np.zeros(rate * 85 // 1000, np.float32), speech, np.zeros(rate // 10, np.float32)])
    assert classifier.classify(padded) == classifier.classify(speech)
    assert max(classifier.classify(speech).items(), key=lambda item: item[1])[0] == "neutral"
    assert without_digital_silence(np.zeros(10, np.float32)).size == 0


@pytest.mark.parametrize("feature_set", ["ComParE_2016", "eGeMAPSv02"])
def test_the_extractor_computes_exactly_what_opensmile_smile_computes(feature_set):
    """FeatureExtractor runs openSMILE's binding without the opensmile package (pandas...): the same
    configuration, so the same names and, bit for bit, the same values (what the models were trained on)."""
    import opensmile
    smile = opensmile.Smile(feature_set=getattr(opensmile.FeatureSet, feature_set),
                            feature_level=opensmile.FeatureLevel.Functionals)
    extractor = FeatureExtractor(feature_set)
    assert extractor.names == list(smile.feature_names)
    for name in ("03a01Fa", "08b02Nb", "10a01Ac", "16b10Td"):
        samples, rate = soundfile.read(shared_data(f"emodb/wav/{name}.wav"), dtype="float32")
        expected = smile.process_signal(samples, rate).to_numpy(dtype=np.float32).reshape(-1)
        got = extractor(samples)
        assert got.dtype == np.float32
        assert np.array_equal(got, np.nan_to_num(expected, nan=0.0, posinf=0.0, neginf=0.0)), name
        assert np.array_equal(extractor((samples * 32768).astype(np.int16)), got)  # int16 in: the same


def test_a_classifier_process_does_not_load_pandas():
    """The memory a classifier holds is its models and openSMILE's library, not pandas and pyarrow."""
    code = ("import sys, numpy as np; from esiaf.speech.classifiers import load_backend; "
            "c = load_backend('onnx', 'esiaf_services/emotion/models/emotion4.onnx'); "
            "c.classify(np.zeros(16000, np.float32) + 0.01); "
            "assert not {'pandas', 'pyarrow', 'audinterface', 'opensmile'} & set(sys.modules), sorted(sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=60)

"""Makes ``tiny.onnx`` + ``tiny.json``: a hand-built two-class ONNX model over eGeMAPS v02.

p(loud) = sigmoid(10 · (mean loudness − 0.3)), as softmax over [0, 10 · (loudness − 0.3)]; every other
feature has weight 0. Run from the repository root with the ``train`` extra (for ``onnx``):
``python esiaf_services/emotion/tests/data/make_tiny_model.py``.
"""
import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

HERE = Path(__file__).resolve().parent
FEATURES = 88
LOUDNESS = 10  # index of loudness_sma3_amean in eGeMAPS v02 functionals
GAIN, THRESHOLD = 10.0, 0.3

weights = np.zeros((FEATURES, 2), np.float32)
weights[LOUDNESS, 1] = GAIN
bias = np.array([0.0, -GAIN * THRESHOLD], np.float32)
graph = helper.make_graph(
    [helper.make_node("MatMul", ["X", "W"], ["logits0"]), helper.make_node("Add", ["logits0", "B"], ["logits"]),
     helper.make_node("Softmax", ["logits"], ["probabilities"], axis=1)],
    "tiny", [helper.make_tensor_value_info("X", TensorProto.FLOAT, [None, FEATURES])],
    [helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, [None, 2])],
    [numpy_helper.from_array(weights, "W"), numpy_helper.from_array(bias, "B")])
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
model.ir_version = 8
onnx.checker.check_model(model)
(HERE / "tiny.onnx").write_bytes(model.SerializeToString())
(HERE / "tiny.json").write_text(json.dumps({"labels": ["quiet", "loud"], "features": "eGeMAPSv02",
                                            "sample_rate_hz": 16000, "loudness_index": LOUDNESS,
                                            "gain": GAIN, "threshold": THRESHOLD}, indent=1) + "\n")

"""Silero VAD (v5/v6 ONNX) on onnxruntime: a speech probability per 32 ms window, state per stream.

The model file is the ``silero_vad.onnx`` that the ``silero-vad`` wheel ships (MIT). That wheel
depends on torch for its own helpers, which ESIAF never imports: setup.sh and the images install
it with ``--no-deps``, and :func:`default_model_path` finds the file without importing the package.

The network takes 512 samples at 16 kHz (256 at 8 kHz) preceded by the last 64 (32) samples of the
previous window, and a recurrent state of shape (2, 1, 128); it returns the window's speech
probability and the next state (as ``OnnxWrapper`` in silero_vad/utils_vad.py does).
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

RATES_HZ = (8000, 16000)


class SileroError(ValueError):
    """The model cannot be found or loaded; the message says why."""


def default_model_path() -> Path:
    spec = importlib.util.find_spec("silero_vad")  # finds the package without running its torch imports
    if spec is None or not spec.submodule_search_locations:
        raise SileroError("the Silero VAD model comes from the silero-vad wheel, which is not installed: "
                          "pip install --no-deps silero-vad==6.2.3 (setup.sh does), or set model_path")
    return Path(next(iter(spec.submodule_search_locations))) / "data" / "silero_vad.onnx"


class SileroModel:
    """One ONNX session, shared by every stream's :class:`SileroStream`."""

    def __init__(self, path: str | Path = ""):
        path = Path(path) if path else default_model_path()
        if not path.is_file():
            raise SileroError(f"Silero VAD model {path} does not exist")
        try:
            import onnxruntime
        except ImportError:
            raise SileroError("the silero backend needs onnxruntime: pip install -e '.[vad]'") from None
        options = onnxruntime.SessionOptions()
        options.inter_op_num_threads = options.intra_op_num_threads = 1
        try:
            self.session = onnxruntime.InferenceSession(str(path), sess_options=options,
                                                        providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime's own error types (InvalidProtobuf, Fail, ...)
            raise SileroError(f"cannot load Silero VAD model {path}: {str(exc).splitlines()[0][:200]}") from None
        names = {i.name for i in self.session.get_inputs()}
        if names != {"input", "state", "sr"}:
            raise SileroError(f"{path} is not a Silero VAD v5/v6 model (inputs {', '.join(sorted(names))}; "
                              f"expected input, state, sr)")
        self.path = path

    def stream(self, sample_rate_hz: int) -> SileroStream:
        return SileroStream(self, sample_rate_hz)


class SileroStream:
    """Speech probabilities of one stream's samples, window by window, whatever the chunk sizes."""

    def __init__(self, model: SileroModel, sample_rate_hz: int):
        if sample_rate_hz not in RATES_HZ:
            raise SileroError(f"Silero VAD takes 8000 or 16000 Hz, not {sample_rate_hz}")
        self.model, self.rate = model, np.array(sample_rate_hz, dtype=np.int64)
        self.window = 512 if sample_rate_hz == 16000 else 256
        self.context = np.zeros((1, 64 if sample_rate_hz == 16000 else 32), dtype=np.float32)
        self.state = np.zeros((2, 1, 128), dtype=np.float32)
        self.pending = np.zeros(0, dtype=np.float32)
        self.last = 0.0

    def probabilities(self, samples: np.ndarray) -> list[float]:
        """The probability of every window that the float samples in [-1, 1] complete."""
        self.pending = np.concatenate([self.pending, np.asarray(samples, dtype=np.float32).reshape(-1)])
        out = []
        while len(self.pending) >= self.window:
            window, self.pending = self.pending[:self.window], self.pending[self.window:]
            x = np.concatenate([self.context, window[None, :]], axis=1)
            probability, self.state = self.model.session.run(None, {"input": x, "state": self.state, "sr": self.rate})
            self.context = x[:, -self.context.shape[1]:]
            out.append(float(probability[0, 0]))
        return out

    def chunk_probability(self, samples: np.ndarray) -> float:
        """A chunk's speech probability: the mean of the windows it completes, else the last window's."""
        completed = self.probabilities(samples)
        if completed:
            self.last = sum(completed) / len(completed)
        return self.last

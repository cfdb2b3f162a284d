"""Silero VAD (v5/v6 ONNX) on onnxruntime: a speech probability per 32 ms window, state per stream.

The model file is the ``silero_vad.onnx`` that the ``silero-vad`` wheel ships (MIT). That wheel
depends on torch for its own helpers, which ESIAF never imports: setup.sh and the images install
it with ``--no-deps``, and :func:`default_model_path` finds the file without importing the package.

The network takes 512 samples at 16 kHz (256 at 8 kHz) preceded by the last 64 (32) samples of the
previous window, and a recurrent state of shape (2, 1, 128); it returns the window's speech
probability and the next state (as ``OnnxWrapper`` in silero_vad/utils_vad.py does).

The network hears level: the same speech 19 dB quieter (about -45 dBFS, a person 10 dB below the robot's
echo once the echo canceller took the echo off microphones set for it) loses most of its speech-like
windows. With a :class:`Leveller` a stream's windows are raised, before the network only, by a slow gain
that brings its loud windows (a percentile of the last seconds' window levels) up to a target level, never
lowering them: a stream as loud as that already is passed as it is.
"""
from __future__ import annotations

import importlib.util
import math
from collections import deque
from pathlib import Path

import numpy as np

RATES_HZ = (8000, 16000)


def window_frames(sample_rate_hz: int) -> int:
    """The samples of one window the network decides on."""
    return 512 if sample_rate_hz == 16000 else 256


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

    def stream(self, sample_rate_hz: int, leveller: Leveller | None = None) -> SileroStream:
        return SileroStream(self, sample_rate_hz, leveller)


class Leveller:
    """A gain for one stream's windows before the network: ``target_db`` (dBFS, window RMS) minus the
    ``percentile`` of the levels of the last ``span_s`` of windows (the stream's loud windows: its speech),
    between 0 and ``max_gain_db``; it starts at 0 and moves by at most ``rise_db_per_s`` up and four times
    that down (the network's recurrent state remembers the level it heard: a gain that jumps, such as the
    20 dB a stream's first second of babble asks for, or one set by each window's own peak, costs it the
    next questions for many seconds). What it pushes past full scale is clipped."""

    def __init__(self, window: int, sample_rate_hz: int, target_db: float = -20.0, max_gain_db: float = 24.0,
                 span_s: float = 20.0, percentile: float = 95.0, rise_db_per_s: float = 2.0):
        if not 0 <= max_gain_db <= 60 or not 0 < percentile <= 100 or span_s <= 0 or rise_db_per_s <= 0:
            raise ValueError(f"bad leveller: max_gain_db {max_gain_db} (0-60), percentile {percentile} (0-100], "
                             f"span_s {span_s} and rise_db_per_s {rise_db_per_s} (> 0)")
        self.target_db, self.max_gain_db, self.percentile = target_db, max_gain_db, percentile
        self.levels: deque[float] = deque(maxlen=max(1, round(span_s * sample_rate_hz / window)))
        self.step_db = rise_db_per_s * window / sample_rate_hz  # per window, up
        self.gain_db = 0.0  # at the last window

    def __call__(self, window: np.ndarray) -> np.ndarray:
        """``window`` (float, full scale 1) raised by the stream's gain at it."""
        rms = float(np.sqrt(np.mean(np.square(window, dtype=np.float64))))
        self.levels.append(20 * math.log10(rms + 1e-9))
        wanted = min(self.max_gain_db, max(0.0, self.target_db - float(np.percentile(self.levels, self.percentile))))
        self.gain_db = min(wanted, self.gain_db + self.step_db) if wanted > self.gain_db else \
            max(wanted, self.gain_db - 4 * self.step_db)
        if self.gain_db == 0.0:
            return window
        return np.clip(window * 10 ** (self.gain_db / 20), -1.0, 1.0).astype(np.float32)


class SileroStream:
    """Speech probabilities of one stream's samples, window by window, whatever the chunk sizes (each window
    raised by ``leveller`` first, when there is one)."""

    def __init__(self, model: SileroModel, sample_rate_hz: int, leveller: Leveller | None = None):
        if sample_rate_hz not in RATES_HZ:
            raise SileroError(f"Silero VAD takes 8000 or 16000 Hz, not {sample_rate_hz}")
        self.model, self.rate = model, np.array(sample_rate_hz, dtype=np.int64)
        self.window = window_frames(sample_rate_hz)
        self.context = np.zeros((1, 64 if sample_rate_hz == 16000 else 32), dtype=np.float32)
        self.state = np.zeros((2, 1, 128), dtype=np.float32)
        self.pending = np.zeros(0, dtype=np.float32)
        self.last = 0.0
        self.leveller = leveller

    def probabilities(self, samples: np.ndarray) -> list[float]:
        """The probability of every window that the float samples in [-1, 1] complete."""
        self.pending = np.concatenate([self.pending, np.asarray(samples, dtype=np.float32).reshape(-1)])
        out = []
        while len(self.pending) >= self.window:
            window, self.pending = self.pending[:self.window], self.pending[self.window:]
            if self.leveller is not None:
                window = self.leveller(window)
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

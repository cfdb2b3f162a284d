"""Echo cancellers behind one small interface: a block of microphone frames and the loudspeaker's
reference for the same instants in, the microphones without the echo out.

Backends (``NAME -> class``, imported lazily; esiaf_services/aec/README.md compares them):

- ``speex`` (the default): speexdsp's MDF echo canceller (Debian's ``libspeexdsp1``, BSD-3-Clause,
  through ctypes), with its preprocessor's residual echo suppression, one state per microphone;
- ``webrtc``: WebRTC's AEC3 (``pywebrtc-audio``, Apache-2.0): a linear filter with its own delay
  estimator and a strong non-linear residual echo suppressor, over all microphones at once (each
  channel keeps its own phase, what ssl and the beamformer need).

Both take and give int16 frames at 16 kHz in blocks of :attr:`Canceller.block_frames`; the reference
is one channel (what the loudspeaker played) and is assumed already aligned to within the backend's
filter length (esiaf_services/aec/align.py does that).
"""
from __future__ import annotations

import ctypes
import ctypes.util
from abc import ABC, abstractmethod

import numpy as np


class BackendError(RuntimeError):
    """A backend that cannot be made (library missing, bad parameters); the message says what to do."""


class Canceller(ABC):
    """Cancels one loudspeaker's echo from ``channels`` microphones."""

    block_frames: int  # frames per call of process()

    def __init__(self, channels: int, sample_rate_hz: int):
        self.channels = channels
        self.sample_rate_hz = sample_rate_hz
        # columns process() gives after the cancelled channels: the same channels as the echo events judge
        # them (speex's ``judge``: its residual suppressor at its defaults), or none
        self.extra_channels = 0

    @abstractmethod
    def process(self, mics: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """``mics`` (block_frames, channels) int16, ``reference`` (block_frames,) int16 -> like ``mics``
        (with ``extra_channels`` more columns after them)."""

    @abstractmethod
    def reset(self) -> None:
        """Forget the echo path (the loudspeaker stopped for long, or the reference jumped)."""


WEBRTC_RATES_HZ = (16000, 32000, 48000)


class WebRtcCanceller(Canceller):
    """AEC3 from pywebrtc-audio: one multi-channel EchoCanceller (10 ms blocks); the reference is given
    on every channel, which AEC3 detects as one loudspeaker."""

    def __init__(self, channels: int, sample_rate_hz: int):
        super().__init__(channels, sample_rate_hz)
        try:
            from pywebrtc_audio import EchoCanceller
        except ImportError:
            raise BackendError("the webrtc echo canceller needs pywebrtc-audio: pip install -e '.[aec]'") from None
        if sample_rate_hz not in WEBRTC_RATES_HZ:
            raise BackendError(f"the webrtc echo canceller takes 16, 32 or 48 kHz, not {sample_rate_hz} Hz")
        self.block_frames = sample_rate_hz // 100
        self._state = EchoCanceller(sample_rate=sample_rate_hz, num_channels=channels)

    def process(self, mics: np.ndarray, reference: np.ndarray) -> np.ndarray:
        far = np.repeat(reference[:, None], self.channels, axis=1)
        return self._state.process(np.ascontiguousarray(mics).reshape(-1), far.reshape(-1)).reshape(mics.shape)

    def reset(self) -> None:
        self._state.reset()


SPEEX_ECHO_SET_SAMPLING_RATE = 24
SPEEX_PREPROCESS_SET_ECHO_STATE = 24
SPEEX_PREPROCESS_SET_NOISE_SUPPRESS = 18
SPEEX_PREPROCESS_SET_ECHO_SUPPRESS = 20
SPEEX_PREPROCESS_SET_ECHO_SUPPRESS_ACTIVE = 22
# the judge's suppressor: speex's own defaults, which fusion's rule on the echo events was calibrated with
JUDGE_RESIDUAL_DB = -40
JUDGE_RESIDUAL_ACTIVE_DB = -15


def _speexdsp() -> ctypes.CDLL:
    name = ctypes.util.find_library("speexdsp") or "libspeexdsp.so.1"
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        raise BackendError("the speex echo canceller needs speexdsp: apt-get install libspeexdsp1") from None
    lib.speex_echo_state_init.restype = ctypes.c_void_p
    lib.speex_echo_state_init.argtypes = [ctypes.c_int, ctypes.c_int]
    lib.speex_echo_state_destroy.argtypes = [ctypes.c_void_p]
    lib.speex_echo_state_reset.argtypes = [ctypes.c_void_p]
    lib.speex_echo_ctl.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
    lib.speex_echo_cancellation.argtypes = [ctypes.c_void_p] + [ctypes.c_void_p] * 3
    lib.speex_preprocess_state_init.restype = ctypes.c_void_p
    lib.speex_preprocess_state_init.argtypes = [ctypes.c_int, ctypes.c_int]
    lib.speex_preprocess_state_destroy.argtypes = [ctypes.c_void_p]
    lib.speex_preprocess_ctl.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
    lib.speex_preprocess_run.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    return lib


class SpeexCanceller(Canceller):
    """speexdsp's MDF filter (``tail_ms`` long) and residual echo suppression, per microphone."""

    def __init__(self, channels: int, sample_rate_hz: int, tail_ms: float = 128.0, block_ms: float = 8.0,
                 suppress_residual: bool = True, residual_db: int = -40, residual_active_db: int = 0,
                 judge: bool = False):
        super().__init__(channels, sample_rate_hz)
        self._lib = _speexdsp()
        self.block_frames = round(sample_rate_hz * block_ms / 1000)
        tail = round(sample_rate_hz * tail_ms / 1000)
        rate = ctypes.c_int(sample_rate_hz)
        self._echo: list[int] = []
        self._pre: list[int] = []
        self._judges: list[int] = []
        for _ in range(channels):
            echo = self._lib.speex_echo_state_init(self.block_frames, tail)
            self._lib.speex_echo_ctl(echo, SPEEX_ECHO_SET_SAMPLING_RATE, ctypes.byref(rate))
            self._echo.append(echo)
            if suppress_residual:
                self._pre.append(self._suppressor(echo, residual_db, residual_active_db))
            if judge:
                self._judges.append(self._suppressor(echo, JUDGE_RESIDUAL_DB, JUDGE_RESIDUAL_ACTIVE_DB))
        self.extra_channels = len(self._judges)
        self._out = np.empty(self.block_frames, dtype=np.int16)
        self._judged = np.empty(self.block_frames, dtype=np.int16)

    def _suppressor(self, echo: int, residual_db: int, residual_active_db: int) -> int:
        """A residual echo suppressor on ``echo``'s estimate: lowering what is left of the echo by
        ``residual_db`` when it is alone, by ``residual_active_db`` while someone near speaks too."""
        pre = self._lib.speex_preprocess_state_init(self.block_frames, self.sample_rate_hz)
        self._lib.speex_preprocess_ctl(pre, SPEEX_PREPROCESS_SET_ECHO_STATE, ctypes.c_void_p(echo))
        noise_db = ctypes.c_int(-3)  # the preprocessor denoises too: barely, ssl and the vad follow
        self._lib.speex_preprocess_ctl(pre, SPEEX_PREPROCESS_SET_NOISE_SUPPRESS, ctypes.byref(noise_db))
        for request, value in ((SPEEX_PREPROCESS_SET_ECHO_SUPPRESS, residual_db),
                               (SPEEX_PREPROCESS_SET_ECHO_SUPPRESS_ACTIVE, residual_active_db)):
            level = ctypes.c_int(value)
            self._lib.speex_preprocess_ctl(pre, request, ctypes.byref(level))
        return pre

    def process(self, mics: np.ndarray, reference: np.ndarray) -> np.ndarray:
        out = np.empty((len(mics), self.channels + self.extra_channels), dtype=np.int16)
        far = np.ascontiguousarray(reference, dtype=np.int16)
        for channel, echo in enumerate(self._echo):
            near = np.ascontiguousarray(mics[:, channel])
            self._lib.speex_echo_cancellation(echo, near.ctypes.data, far.ctypes.data, self._out.ctypes.data)
            if self._judges:
                self._judged[:] = self._out
                self._lib.speex_preprocess_run(self._judges[channel], self._judged.ctypes.data)
                out[:, self.channels + channel] = self._judged
            if self._pre:
                self._lib.speex_preprocess_run(self._pre[channel], self._out.ctypes.data)
            out[:, channel] = self._out
        return out

    def reset(self) -> None:
        for echo in self._echo:
            self._lib.speex_echo_state_reset(echo)

    def __del__(self) -> None:
        lib = getattr(self, "_lib", None)
        if lib is not None:
            for pre in self._pre + self._judges:
                lib.speex_preprocess_state_destroy(pre)
            for echo in self._echo:
                lib.speex_echo_state_destroy(echo)


BACKENDS: dict[str, type[Canceller]] = {"speex": SpeexCanceller, "webrtc": WebRtcCanceller}

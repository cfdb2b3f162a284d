"""One stream's echo cancellation: the reference lined up (align.py), then a backend (backends.py).

:meth:`StreamCanceller.process` takes microphone chunks of any length, stamped with their capture
times, and gives back cancelled frames in order; frames wait for a whole backend block
(10 ms for webrtc), so the output may lag the input by less than a block until :meth:`flush`. With
``retrain_passes``, a new alignment (the delay's first estimate, a jump of the line) resets the backend and
adapts it again over the last ``retrain_s`` of microphone frames, the reference read at the new alignment.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from esiaf_services.aec.align import FIT_MIN_S, NS, OUTLIER_MS, DelayTracker, ReferenceTrack
from esiaf_services.aec.backends import Canceller

FULL_SCALE = 32768.0
RETRAIN_MS = 1.0  # the line moved the delay this much between two chunks: the filter learnt a wrong alignment


class StreamCanceller:
    def __init__(self, canceller: Canceller, sample_rate_hz: int, *, max_delay_ms: float = 400.0,
                 lead_ms: float = 4.0, estimate_delay: bool = True, max_held_s: float = 600.0,
                 retrain_s: float = 1.0, retrain_passes: int = 0, fit_min_s: float = FIT_MIN_S,
                 outlier_ms: float = OUTLIER_MS):
        self.canceller = canceller
        self.rate = sample_rate_hz
        self.track = ReferenceTrack(sample_rate_hz, max_held_s=max_held_s)
        self.tracker = DelayTracker(sample_rate_hz, max_delay_ms=max_delay_ms, fit_min_s=fit_min_s,
                                    outlier_ms=outlier_ms)
        self.estimate_delay = estimate_delay
        self.lead = lead_ms * sample_rate_hz / 1000  # the reference reaches the canceller this much before its echo
        self._mic_history = np.zeros(0)  # the first microphone's last window, for the delay tracker
        self._pending_mics = np.zeros((0, canceller.channels), dtype=np.int16)
        self._pending_reference = np.zeros(0, dtype=np.int16)
        self.retrain_frames = int(retrain_s * sample_rate_hz)
        self.retrain_passes = retrain_passes
        self.retrained = 0  # how often the filter was reset and trained again on the history
        self._history: deque[tuple[int, np.ndarray]] = deque()  # the last retrain_s of chunks (start_ns, mics)
        self._history_frames = 0
        self._delay_before: float | None = None  # the delay the last chunk was read at (None: not yet known)

    def add_reference(self, start_ns: int, samples: np.ndarray) -> None:
        """What the loudspeaker played from ``start_ns`` (float, full scale 1)."""
        self.track.add(start_ns, samples)

    def delay_ns(self, time_ns: int) -> int:
        """The estimated delay of the echo after the reference's stamps at a capture time (0 until estimated)."""
        return int(float(self.tracker.delay_at(np.array(self._seconds(time_ns)))) * NS / self.rate)

    def converged_at(self, time_ns: int, settle_s: float) -> bool:
        """Whether ``settle_s`` of capture time have passed at ``time_ns`` since the delay was first estimated
        (the filter adapts on the lined-up reference from then on)."""
        first = self.tracker.first_known_s
        return first is not None and self._seconds(time_ns) - first >= settle_s

    def reference_needed_until(self, end_ns: int) -> int:
        """The stamp up to which the reference must be in to cancel microphone frames up to ``end_ns``."""
        return end_ns + int(self.lead * NS / self.rate) - self.delay_ns(end_ns)  # later where the echo comes early

    def _seconds(self, time_ns: int) -> float:
        return 0.0 if self.track.origin_ns is None else (time_ns - self.track.origin_ns) / NS

    def _reference_for(self, start_ns: int, frames: int) -> np.ndarray:
        """The reference at the instants of ``frames`` microphone frames from ``start_ns``, the estimated delay
        (which drift moves) taken off and ``lead`` added."""
        if self.track.origin_ns is None or not frames:
            return np.zeros(frames)
        middle_s = self._seconds(start_ns) + frames / 2 / self.rate
        delay = float(self.tracker.delay_at(np.array(middle_s)))
        return self.track.read(self.track.index_at(start_ns) - delay + self.lead, frames)

    def _track_delay(self, start_ns: int, mics: np.ndarray) -> None:
        window = self.tracker.window
        self._mic_history = np.concatenate([self._mic_history, mics[:, 0] / FULL_SCALE])[-window:]
        if self.track.origin_ns is None:
            return
        end_ns = start_ns + len(mics) * NS // self.rate
        end_index = round(self.track.index_at(end_ns))
        reference = self.track.slice(end_index - window - self.tracker.max_lag,
                                     window + self.tracker.max_lag + self.tracker.min_lag)
        self.tracker.offer(self._seconds(end_ns), self._mic_history, reference, len(mics))

    def process(self, start_ns: int, mics: np.ndarray) -> np.ndarray:
        """``mics`` (frames, channels) int16 captured from ``start_ns`` -> the cancelled frames now ready."""
        if self.estimate_delay:
            self._track_delay(start_ns, mics)
        reference = self._pcm_reference(start_ns, len(mics))
        if self.track.origin_ns is not None:  # what the delay tracker, the next chunks and a retraining may read
            self.track.forget_before(round(self.track.index_at(start_ns)) - 2 * self.tracker.max_lag
                                     - max(self.tracker.window, self.retrain_frames if self.retrain_passes else 0))
        self._pending_mics = np.concatenate([self._pending_mics, mics])
        self._pending_reference = np.concatenate([self._pending_reference, reference])
        self._remember(start_ns, mics)
        if self._alignment_changed(start_ns):
            self._retrain()
        return self._run(len(self._pending_mics) // self.canceller.block_frames)

    def _pcm_reference(self, start_ns: int, frames: int) -> np.ndarray:
        reference = np.clip(np.rint(self._reference_for(start_ns, frames) * FULL_SCALE), -32768, 32767)
        return reference.astype(np.int16)

    def _remember(self, start_ns: int, mics: np.ndarray) -> None:
        """Keeps the last ``retrain_s`` of microphone chunks (and always those whose frames still wait)."""
        if not self.retrain_passes:
            return
        self._history.append((start_ns, mics))
        self._history_frames += len(mics)
        while len(self._history) > 1 and self._history_frames - len(self._history[0][1]) >= \
                max(self.retrain_frames, len(self._pending_mics)):
            self._history_frames -= len(self._history.popleft()[1])

    def _alignment_changed(self, start_ns: int) -> bool:
        """Whether the delay became known, or the line jumped, since the last chunk: the filter has been
        adapting to a reference at the wrong place."""
        if not self.tracker.known:
            return False
        delay = float(self.tracker.delay_at(np.array(self._seconds(start_ns))))
        before, self._delay_before = self._delay_before, delay
        return before is None or abs(delay - before) > RETRAIN_MS * self.rate / 1000

    def _retrain(self) -> None:
        """The filter forgets what it learnt and adapts ``retrain_passes`` times over the last ``retrain_s`` of
        microphone frames with the reference read at the new alignment (their output was published already;
        what it gives now is dropped): it starts where it would be had the alignment been known then, instead
        of converging again on the next seconds of the robot's speech."""
        if not self.retrain_passes or not self._history:
            return
        self.retrained += 1
        mics = np.concatenate([chunk for _, chunk in self._history])
        reference = np.concatenate([self._pcm_reference(start, len(chunk)) for start, chunk in self._history])
        ran = len(mics) - len(self._pending_mics)  # frames the canceller had before these
        first = ran % self.canceller.block_frames
        self.canceller.reset()
        size = self.canceller.block_frames
        for _ in range(self.retrain_passes):
            for at in range(first, ran, size):
                self.canceller.process(mics[at:at + size], reference[at:at + size])
        self._pending_reference = reference[ran:]

    def flush(self) -> np.ndarray:
        """The frames still waiting for a whole block, cancelled with silence padded after them."""
        waiting, block = len(self._pending_mics), self.canceller.block_frames
        if not waiting % block:
            return self._run(waiting // block)
        pad = block - waiting % block
        self._pending_mics = np.concatenate([self._pending_mics, np.zeros((pad, self.canceller.channels), np.int16)])
        self._pending_reference = np.concatenate([self._pending_reference, np.zeros(pad, np.int16)])
        return self._run(len(self._pending_mics) // block)[:waiting]

    @property
    def waiting_frames(self) -> int:
        return len(self._pending_mics)

    def _run(self, blocks: int) -> np.ndarray:
        size = self.canceller.block_frames
        out = [self.canceller.process(self._pending_mics[i * size:(i + 1) * size],
                                      self._pending_reference[i * size:(i + 1) * size]) for i in range(blocks)]
        self._pending_mics = self._pending_mics[blocks * size:]
        self._pending_reference = self._pending_reference[blocks * size:]
        return np.concatenate(out) if out else np.zeros((0, self.canceller.channels + self.canceller.extra_channels),
                                                        dtype=np.int16)

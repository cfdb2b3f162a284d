"""What the canceller's output says about a person speaking while the robot plays: its ``echo`` events.

While the canceller cancels a stream, it measures its own output in blocks of ``BLOCK_MS`` of capture
time: the level over all channels (dB, 96 = full scale, the ssl service's scale), how far that stands
above the output's floor (the ``FLOOR_PERCENTILE`` of the last ``FLOOR_BLOCKS`` blocks' levels: the
noise and the residual echo between the robot's words), how much the canceller took off (the
microphones' level minus the output's: near 0 dB where there was no echo, or where the canceller lost
it for a moment and the robot's voice passed), and whether the canceller has had
``CONVERGE_S`` of capture time since its delay tracker's first estimate (speex's filter needs 1-2 s
once the delay is known; before, the robot's own echo passes nearly whole).

A converged canceller takes the robot's voice 25-40 dB down; what is left in its output well above
its floor is someone else: fusion's rule for the robot's voice (orchestrator ``fusion/playback.py``)
takes an utterance in which the robot spoke for a person's where these events say so. Measured on
``bench/robot_speaks.py``'s scenes (the person 10 dB below the echo, babble 10 dB below the person; the
90th percentile of a segment's blocks): people asking while the robot spoke stood 16-28 dB above the
floor with 11-19 dB taken off, the robot's converged residual that the vad took for speech 10 dB; a
moment where the canceller lost the echo stood 32 dB above its floor, but with 2-5 dB taken off in its
loudest blocks. With the fast start (the default: the filter converged sooner, the floor lower) the
robot's residual can stand 16-23 dB above the floor too, but with 22-24 dB taken off, more than a person
10 dB below the echo leaves: fusion counts such blocks neither way (its ``PERSON_MAX_CANCELLED_DB``).
Pure: no I/O.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

BLOCK_MS = 256.0
FLOOR_BLOCKS = 40  # about 10 s of the canceller's output
FLOOR_MIN_BLOCKS = 8  # no floor (and no above_floor_db) before this many blocks
FLOOR_PERCENTILE = 10.0
CONVERGE_S = 2.0
FULL_SCALE_DB = 96.0
NS = 1_000_000_000


@dataclass(frozen=True)
class EchoBlock:
    """One block of the canceller's output: its capture span, level, height above the floor, what the
    canceller took off, and whether it had converged (``above_floor_db`` is None until the floor is known)."""

    start_ns: int
    end_ns: int
    level_db: float
    above_floor_db: float | None
    cancelled_db: float
    converged: bool


class EchoMeter:
    """One stream's blocks of cancelled output, as :meth:`add` completes them."""

    def __init__(self, sample_rate_hz: int):
        self.rate = sample_rate_hz
        self.block_frames = round(BLOCK_MS * sample_rate_hz / 1000)
        self._energy = 0.0  # summed square of the current block's samples (full scale 1), over channels
        self._energy_in = 0.0  # ... of the microphones' samples the canceller had
        self._values = 0
        self._frames = 0
        self._start_ns: int | None = None
        self._next_ns: int | None = None  # where the current block goes on; a gap (a pass-through) drops it
        self._levels: deque[float] = deque(maxlen=FLOOR_BLOCKS)

    def add(self, start_ns: int, mics: np.ndarray, frames: np.ndarray, converged: bool) -> list[EchoBlock]:
        """``mics`` (frames, channels) int16 captured from ``start_ns`` and ``frames``, the same cancelled; the
        blocks completed."""
        blocks = []
        done = 0
        if self._next_ns is not None and abs(start_ns - self._next_ns) > NS // self.rate:
            self._reset()
        self._next_ns = start_ns + len(frames) * NS // self.rate
        samples = frames.astype(np.float64) / 32768.0
        heard = mics.astype(np.float64) / 32768.0
        while done < len(samples):
            if self._start_ns is None:
                self._start_ns = start_ns + done * NS // self.rate
            take = min(self.block_frames - self._frames, len(samples) - done)
            part = samples[done:done + take]
            self._energy += float(np.sum(part * part))
            self._energy_in += float(np.sum(heard[done:done + take] ** 2))
            self._values += part.size
            self._frames += take
            done += take
            if self._frames == self.block_frames:
                end_ns = start_ns + done * NS // self.rate
                blocks.append(self._close(end_ns, converged))
        return blocks

    def _close(self, end_ns: int, converged: bool) -> EchoBlock:
        assert self._start_ns is not None
        level = FULL_SCALE_DB + 10 * math.log10(self._energy / max(self._values, 1) + 1e-20)
        level_in = FULL_SCALE_DB + 10 * math.log10(self._energy_in / max(self._values, 1) + 1e-20)
        self._levels.append(level)
        floor = (float(np.percentile(np.array(self._levels), FLOOR_PERCENTILE))
                 if len(self._levels) >= FLOOR_MIN_BLOCKS else None)
        block = EchoBlock(self._start_ns, end_ns, round(level, 2), None if floor is None else round(level - floor, 2),
                          round(level_in - level, 2), converged)
        self._reset()
        return block

    def _reset(self) -> None:
        self._energy, self._energy_in, self._values, self._frames, self._start_ns = 0.0, 0.0, 0, 0, None

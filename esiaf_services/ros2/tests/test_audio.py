"""The voices' audio store: a span cut out by capture time, and its bounds against a peer that lies."""
from __future__ import annotations

import numpy as np

from esiaf_services.ros2.audio import AudioBuffer

RATE = 16000
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def chunks(buffer: AudioBuffer, stream_id: str, seconds: float, chunk_ms: int = 20) -> np.ndarray:
    """Adds ``seconds`` of a counting signal in chunks from T0; returns the samples."""
    samples = (np.arange(int(seconds * RATE)) % 30000).astype("<i2")
    step = RATE * chunk_ms // 1000
    for first in range(0, len(samples), step):
        part = samples[first:first + step]
        start = T0 + first * 1_000_000_000 // RATE
        buffer.add(stream_id, start, start + len(part) * 1_000_000_000 // RATE, part.tobytes())
    return samples


def test_a_span_is_cut_to_the_sample_across_chunks():
    buffer = AudioBuffer(RATE, keep_s=10, max_streams=4)
    samples = chunks(buffer, "a", 2.0)
    cut = np.frombuffer(buffer.cut("a", T0 + 250 * MS, T0 + 1250 * MS), dtype="<i2")
    assert np.array_equal(cut, samples[4000:20000])
    assert buffer.reached_ns("a") == T0 + 2000 * MS and buffer.reached_ns("b") == 0
    assert buffer.cut("b", T0, T0 + 1000 * MS) == b""


def test_only_the_latest_keep_s_is_kept_and_only_max_streams_streams():
    buffer = AudioBuffer(RATE, keep_s=1, max_streams=2)
    samples = chunks(buffer, "a", 3.0)
    cut = np.frombuffer(buffer.cut("a", T0, T0 + 3000 * MS), dtype="<i2")
    assert 0.98 * RATE <= len(cut) <= RATE and np.array_equal(cut, samples[-len(cut):])
    assert buffer.kept_bytes == len(cut) * 2
    chunks(buffer, "b", 0.1)
    chunks(buffer, "c", 0.1)
    assert buffer.cut("a", T0, T0 + 3000 * MS) == b""  # the least recently heard stream went


def test_chunks_whose_spans_lie_are_bounded_by_bytes_and_going_back_starts_afresh():
    buffer = AudioBuffer(RATE, keep_s=1, max_streams=2)
    big = np.ones(RATE, dtype="<i2").tobytes()  # 1 s of samples claimed to last 1 ns, ten times
    for n in range(10):
        buffer.add("a", T0 + n, T0 + n + 1, big)
    assert buffer.kept_bytes <= RATE * 2
    buffer.add("a", T0 - 10 * MS, T0 - 5 * MS, np.zeros(80, dtype="<i2").tobytes())
    assert buffer.restarted == 1 and buffer.reached_ns("a") == T0 - 5 * MS

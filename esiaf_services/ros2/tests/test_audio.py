"""The voices' audio: the store (a span cut out by capture time, its bounds against a peer that lies),
and the bridge waiting for an utterance's audio (bounded too)."""
from __future__ import annotations

import json
import random
from typing import Any

import numpy as np
import pytest

from esiaf_services.ros2.audio import AudioBuffer
from esiaf_services.ros2.service import Ros2, Ros2Settings

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


class Bridge(Ros2):
    """The ros2 service with an audio topic (a real DDS participant on a domain of its own), what it
    publishes kept to look at."""

    def __init__(self, **settings: Any) -> None:
        pytest.importorskip("cyclonedds", reason="the ros2 extra (pip install 'esiaf[ros2]')")
        super().__init__(Ros2Settings(audio_topic="beamformer/audio", **settings), random.randint(100, 200))
        self.sent: list[tuple[str, Any]] = []

    def publish(self, publications: list[tuple[str, Any]]) -> None:
        self.sent += publications
        super().publish(publications)

    def fused(self, n: int, now_s: float, seconds: float = 1.0) -> None:
        start = T0 + n * 2000 * MS
        self.handle(json.dumps({
            "type": "fused_result", "id": n, "revision": 1, "stream_id": "s",
            "anchor": {"type": "speech", "span": {"start_ns": start, "end_ns": start + int(seconds * 1e9)},
                       "speech": {"hypotheses": [{"text": f"sentence {n}", "probability": 0.5, "words": []}]}},
            "results": {}, "aggregates": {"voice_id": {"label": "voice-1"}}}), now_s)

    def audio_frames(self) -> list[int]:
        return [len(sample.data) // 2 for topic, sample in self.sent if topic.endswith("/audio")]


def test_an_utterance_s_audio_waits_for_its_span_then_goes_at_its_deadline_with_what_came():
    bridge = Bridge(audio_wait_s=0.5)
    buffer = bridge.audio
    assert buffer is not None
    bridge.fused(0, now_s=0.0)  # its speech at once, its audio not yet heard
    assert [topic for topic, _ in bridge.sent][-2:] == ["/humans/voices/voice_1/speech",
                                                             "/humans/voices/voice_1/is_speaking"]
    buffer.add("s", T0, T0 + 500 * MS, np.ones(8000, dtype="<i2").tobytes())
    bridge.publish_audio(0.1)
    assert bridge.audio_frames() == []  # half of the span: it waits
    buffer.add("s", T0 + 500 * MS, T0 + 1500 * MS, np.ones(16000, dtype="<i2").tobytes())
    bridge.publish_audio(0.2)
    assert bridge.audio_frames() == [16000]  # the span, 1 s, to the sample
    bridge.fused(1, now_s=1.0, seconds=1.0)  # 2..3 s: no audio comes
    bridge.publish_audio(1.4)
    assert bridge.audio_frames() == [16000]
    bridge.publish_audio(1.6)  # its deadline passed: nothing to send, refused
    assert bridge.audio_frames() == [16000] and bridge.refused["no_audio"] == 1 and not bridge.pending


def test_past_max_pending_audio_the_oldest_waiting_utterance_is_refused():
    bridge = Bridge(max_pending_audio=2)
    for n in range(3):
        bridge.fused(n, now_s=0.0)
    assert bridge.refused["audio_pending_full"] == 1
    assert [utterance.start_ns for utterance, _ in bridge.pending] == [T0 + 2000 * MS, T0 + 4000 * MS]

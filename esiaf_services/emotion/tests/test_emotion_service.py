"""The emotion/gender component's handlers: one label per segment, "nothing" for what cannot be judged."""
from __future__ import annotations

import numpy as np
import pytest
import soundfile

from esiaf import Audio, AudioFormat, load_settings
from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.testing import shared_data
from esiaf_services.emotion.service import Emotion
from esiaf_services.gender.service import Gender

FMT = AudioFormat(16000, "int16")
ORIGIN_NS = 1_700_000_000_000_000_000
TOY = "esiaf_services.emotion.tests.toy_backend:LoudnessClassifier"


def play_segment(component, samples: np.ndarray, start_s: float, stream_id: str = "s", chunk: int = 320):
    """Feeds ``samples`` as 20 ms chunks of one VAD segment, the last one closing it."""
    pcm = np.clip(samples * 32768, -32768, 32767).astype(np.int16)
    start_ns = ORIGIN_NS + round(start_s * 1e9)
    end_ns = start_ns + len(pcm) * 1_000_000_000 // 16000
    for offset in range(0, len(pcm), chunk):
        piece = pcm[offset:offset + chunk]
        meta = pb.AudioMeta()
        last = offset + chunk >= len(pcm)
        if last:
            meta.segmentation_ended = True
            meta.segment.start_ns, meta.segment.end_ns = start_ns, end_ns
        audio = Audio("vad/speech", stream_id, "vad-1", offset // chunk + 1, start_ns + offset * 62_500,
                      start_ns + (offset + len(piece)) * 62_500, FMT, piece.tobytes(), meta)
        component.on_audio(audio)  # the order the SDK calls them in
        if last:
            component.on_segment_end(audio)
    return start_ns, end_ns


def make(cls, **settings):
    component = cls(load_settings(cls.Settings, cls.service, env={}, **settings))
    component.setup()
    component.emitted = []
    component.emit = lambda kind, span, stream_id=None, **payload: component.emitted.append((kind, span, payload))
    return component


def emodb(name: str) -> np.ndarray:
    samples, _ = soundfile.read(shared_data(f"emodb/wav/{name}.wav"), dtype="float32")
    return samples


def test_a_segment_gets_one_emotion_result_spanning_it():
    emotion = make(Emotion)
    assert emotion.classifier.labels == ("angry", "happy", "neutral", "sad")
    span = play_segment(emotion, emodb("03a01Wa"), start_s=1.0)
    (kind, got_span, payload), = emotion.emitted
    result = payload["emotion"]
    assert kind == "emotion" and got_span == span
    assert set(result["class_probabilities"]) == {"angry", "happy", "neutral", "sad"}
    assert sum(result["class_probabilities"].values()) == pytest.approx(1.0, abs=1e-4)
    assert result["label"] == max(result["class_probabilities"], key=result["class_probabilities"].get)
    assert result["probability"] == result["class_probabilities"][result["label"]]


def test_too_short_and_silent_segments_are_covered_by_nothing():
    emotion = make(Emotion, backend="python", model=TOY)
    short = play_segment(emotion, 0.3 * np.ones(3200, np.float32), start_s=0.0)  # 200 ms
    noise = np.random.default_rng(1).normal(0, 0.0005, 16000).astype(np.float32)  # -60 dBFS for 1 s
    quiet = play_segment(emotion, noise, start_s=2.0)
    assert [(k, s, p) for k, s, p in emotion.emitted] == [
        ("emotion", short, {"nothing": "too short to judge (200 ms < 500 ms)"}),
        ("emotion", quiet, {"nothing": f"silence (peak {emotion.unusable(noise).split()[2]} dB < 45 dB)"})]


def test_streams_are_segmented_apart_and_an_unclosed_segment_ends_with_its_stream():
    gender = make(Gender, backend="python", model=TOY)
    loud = 0.3 * np.sin(np.arange(16000) / 5).astype(np.float32)
    play_segment(gender, loud, start_s=0.0, stream_id="a")
    assert gender.emitted[-1][2]["gender"]["label"] == "loud"
    pcm = (0.03 * 32768 * np.ones(16000)).astype(np.int16)  # loud enough to judge, quiet for the toy
    gender.on_audio(Audio("vad/speech", "b", "vad-1", 1, ORIGIN_NS, ORIGIN_NS + 10**9, FMT, pcm.tobytes()))
    end = Audio("vad/speech", "b", "vad-1", 2, ORIGIN_NS + 10**9, ORIGIN_NS + 10**9, FMT, b"")
    gender.on_end_of_stream("b", end)
    kind, span, payload = gender.emitted[-1]
    assert kind == "gender" and span == (ORIGIN_NS, ORIGIN_NS + 10**9) and payload["gender"]["label"] == "quiet"
    assert not gender.utterances


def test_gender_uses_its_bundled_model():
    gender = make(Gender)
    assert gender.classifier.labels == ("female", "male")
    play_segment(gender, emodb("08a01Fd"), start_s=0.0)
    assert gender.emitted[0][2]["gender"]["label"] in ("female", "male")

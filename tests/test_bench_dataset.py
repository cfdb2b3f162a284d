"""bench/dataset.py's scoring and loss counters, on known answers (no pipeline, no audio)."""
from __future__ import annotations

import math

import pytest

dataset = pytest.importorskip("bench.dataset", reason="bench/dataset.py needs the analysers' packages")


def utterance(kind: str, start_s: float, end_s: float, **labels: str) -> dict:
    return {"kind": kind, "start_s": start_s, "end_s": end_s, "azimuth_deg": 90.0, "text": labels.get("text", ""),
            "emotion": labels.get("emotion", ""), "gender": labels.get("gender", "male")}


def result(start_s: float, end_s: float, **fields) -> dict:
    return {"start_s": start_s, "end_s": end_s, "text": "", "azimuth_deg": 100.0, "emotion": None, "gender": "male",
            "completion": "complete", **fields}


def test_score_matches_each_utterance_with_the_result_overlapping_it_most():
    truth = [utterance("robocup", 1.0, 3.0, text="What is a chatbot?"),
             utterance("emodb", 6.0, 9.0, emotion="sad", gender="female"),
             utterance("emodb", 12.0, 14.0, emotion="angry")]
    results = [result(0.9, 3.1, text="what is a chatbot", azimuth_deg=350.0),  # 100° off
               result(6.0, 6.5, emotion="happy", gender="male"),  # a split: the smaller part
               result(6.9, 9.0, emotion="sad", gender="female", completion="timed_out", revision=2),
               result(20.0, 21.0)]  # overlaps nothing
    figures = dataset.score(truth, results)
    assert figures["utterances"] == 3 and figures["results"] == 4
    assert figures["lost"] == 1 and figures["spurious"] == 1
    assert figures["complete"] == 3 and figures["not_complete"] == 1 and figures["revised"] == 1
    assert figures["text_right"] == 1.0
    assert figures["emotion_right"] == 1.0 and figures["gender_right"] == 1.0
    assert figures["direction_error_deg"] == pytest.approx((100.0 + 10.0) / 2)
    assert figures["direction_within_15"] == 0.5


def test_score_of_nothing_heard():
    figures = dataset.score([utterance("robocup", 1.0, 2.0, text="hello")], [])
    assert figures["lost"] == 1 and math.isnan(figures["text_right"]) and math.isnan(figures["direction_error_deg"])


def test_counters_keep_the_nonzero_losses_only():
    stats = {"/fusions/stats": {"counters": {"fused": 3, "bad_json": 0}},
             "/components": {"items": [{"name": "vad", "info": {"results_dropped": 2, "results_sent": 9},
                                        "outputs": [{"topic": "vad/speech", "dropped": 0}]}]}}
    assert dataset.counters(stats) == {"/components.items[vad].info.results_dropped": 2}

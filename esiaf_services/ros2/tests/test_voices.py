"""What a fused result becomes on the voice topics (esiaf_services/ros2/voices.py): ids, the speech and
its revisions, the direction, the labels, partials and the tracked list."""
from __future__ import annotations

import math

import pytest

from esiaf_services.ros2.messages import FEMALE
from esiaf_services.ros2.voices import Unmappable, Voices, namespace, segment

START_NS = 1_700_000_000_250_000_000


def fused(revision: int = 1, aggregates: dict | None = None, text: str = "go to the kitchen") -> dict:
    return {"type": "fused_result", "id": 4, "revision": revision, "stream_id": "kitchen robot",
            "anchor": {"type": "speech", "span": {"start_ns": START_NS, "end_ns": START_NS + 10**9},
                       "speech": {"hypotheses": [{"text": text, "probability": 0.75, "words": []}]}},
            "results": {}, "aggregates": aggregates or {}}


def topics(publications) -> list[str]:
    return [topic for topic, _ in publications]


@pytest.mark.parametrize(("text", "name"), [("voice-2", "voice_2"), ("Anna", "Anna"), ("Zoë B.", "Zo_B"),
                                            ("7th", "v7th"), ("--", "unknown"), ("a__b_", "a_b")])
def test_a_voice_id_is_one_valid_ros_name_segment(text, name):
    assert segment(text) == name


def test_a_namespace_setting_becomes_a_prefix():
    assert namespace("") == ""
    assert namespace("/robot-1/") == "/robot_1"
    assert namespace("site/robot 2") == "/site/robot_2"


def test_the_first_revision_says_the_speech_between_is_speaking_true_and_false():
    out = Voices().fused(fused(aggregates={"voice_id": {"label": "voice-2", "probability": 1.0}}), 0.0)
    assert topics(out) == ["/humans/voices/voice_2/is_speaking", "/humans/voices/voice_2/speech",
                           "/humans/voices/voice_2/is_speaking"]
    assert [out[0][1].data, out[2][1].data] == [True, False]
    speech = out[1][1]
    assert (speech.final, speech.incremental, speech.confidence, speech.language) == \
        ("go to the kitchen", "", 0.75, "en-US")
    assert (speech.header.stamp.sec, speech.header.stamp.nanosec) == (1_700_000_000, 250_000_000)


def test_without_a_voice_the_track_names_it_and_without_a_track_unknown():
    ssl = {"azimuth_deg": 90.0, "elevation_deg": 0.0, "source_id": "s3"}
    assert topics(Voices().fused(fused(aggregates={"ssl": ssl}), 0.0))[1] == "/humans/voices/track_s3/speech"
    assert topics(Voices().fused(fused(aggregates={"voice_id": {"label": "unknown"}}), 0.0))[1] == \
        "/humans/voices/unknown/speech"


def test_a_later_revision_says_no_speech_again_only_what_came_late():
    out = Voices().fused(fused(revision=2, aggregates={"gender": {"label": "female", "probability": 0.8}}), 0.0)
    assert topics(out) == ["/humans/voices/unknown/softbiometrics"]
    assert (out[0][1].gender, out[0][1].gender_confidence) == (FEMALE, pytest.approx(0.8))


def test_the_direction_is_a_unit_vector_in_the_array_frame_and_background_is_none():
    ssl = {"azimuth_deg": 90.0, "elevation_deg": 30.0, "source_id": "s1"}
    out = dict(Voices(frame_id="head_mics").fused(fused(revision=2, aggregates={"ssl": ssl}), 0.0))
    direction = out["/humans/voices/track_s1/direction"]
    assert direction.header.frame_id == "head_mics"
    v = direction.vector
    assert (v.x, v.y, v.z) == pytest.approx((0.0, math.cos(math.radians(30)), 0.5), abs=1e-9)
    assert Voices().fused(fused(revision=2, aggregates={"ssl": {**ssl, "background": True}}), 0.0) == []


def test_the_emotion_is_an_expression():
    out = dict(Voices().fused(fused(revision=2, aggregates={"emotion": {"label": "happy", "probability": 0.6}}),
                              0.0))
    expression = out["/humans/voices/unknown/expression"]
    assert (expression.expression, expression.confidence) == ("happy", pytest.approx(0.6))


def test_streams_in_namespaces_of_their_own():
    voices = Voices(prefix="/site", per_stream=True)
    assert topics(voices.fused(fused(), 0.0))[1] == "/site/kitchen_robot/humans/voices/unknown/speech"
    assert topics(voices.tracked(1.0, START_NS)) == ["/site/kitchen_robot/humans/voices/tracked"]


def test_partials_speak_as_unknown_their_close_ends_it_and_the_final_goes_to_the_named_voice():
    voices = Voices()
    partial = {"type": "partial", "stream_id": "kitchen robot", "span": {"start_ns": START_NS, "end_ns": START_NS},
               "text": "go to", "stable": "", "closed": False}
    first, second = voices.partial(partial, 0.0), voices.partial({**partial, "text": "go to the"}, 0.1)
    assert topics(first) == ["/humans/voices/unknown/is_speaking", "/humans/voices/unknown/speech"]
    assert topics(second) == ["/humans/voices/unknown/speech"] and second[0][1].incremental == "go to the"
    closed = voices.partial({**partial, "text": "", "closed": True}, 0.2)
    assert topics(closed) == ["/humans/voices/unknown/is_speaking"] and closed[0][1].data is False
    assert voices.partial({**partial, "text": "", "closed": True}, 0.25) == []  # closed once
    final = voices.fused(fused(aggregates={"voice_id": {"label": "voice-1"}}), 0.3)
    assert topics(final) == ["/humans/voices/voice_1/is_speaking", "/humans/voices/voice_1/speech",
                             "/humans/voices/voice_1/is_speaking"]
    assert final[0][1].data is True and final[2][1].data is False


def test_the_tracked_list_forgets_voices_unheard_for_long():
    voices = Voices(forget_after_s=30.0)
    voices.fused(fused(aggregates={"voice_id": {"label": "Anna"}}), 0.0)
    voices.fused(fused(aggregates={"voice_id": {"label": "voice-1"}}), 20.0)
    assert voices.tracked(25.0, START_NS)[0][1].ids == ["Anna", "voice_1"]
    assert voices.tracked(40.0, START_NS)[0][1].ids == ["voice_1"]
    assert voices.tracked(60.0, START_NS)[0][1].ids == []


@pytest.mark.parametrize("message", [{}, {"stream_id": "s"}, {"stream_id": 3, "anchor": {"span": {"start_ns": 1}}},
                                     {"stream_id": "s", "anchor": {"span": {"start_ns": "later"}}},
                                     {**fused(), "aggregates": []}])
def test_what_cannot_be_mapped_is_one_error_with_a_reason(message):
    with pytest.raises(Unmappable) as caught:
        Voices().fused(message, 0.0)
    assert caught.value.reason == "bad_fused_result"

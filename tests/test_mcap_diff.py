"""The diff of recorded and replayed fused results, on utterances with known differences (no pipeline)."""
from __future__ import annotations

from esiaf.tools.mcap_diff import Utterance, diff


def said(start_s: float, text: str, direction_deg: float | None = None, voice: str = "voice-1") -> Utterance:
    return Utterance(start_s, start_s + 1.5, text, direction_deg, voice)


RECORDED = [said(1.0, "how big is the rcmp", 0.0), said(5.0, "what is a chatbot", 90.0),
            said(9.0, "who invented the compiler", 180.0), said(13.0, "is mark zuckerberg a robot", 355.0)]


def test_the_same_utterances_give_no_difference():
    assert diff(RECORDED, RECORDED) == ["diff: 4 recorded utterances, 4 replayed, 0 differences"]


def test_directions_within_the_tolerance_across_north_are_the_same():
    replayed = [*RECORDED[:3], said(13.2, "is mark zuckerberg a robot", 3.0)]  # 8 degrees apart, through 0
    assert diff(RECORDED, replayed)[-1].endswith("0 differences")


def test_each_kind_of_change_is_one_line():
    replayed = [said(1.1, "how big is the rcmp", 0.0, voice="Anna"),  # another voice
                said(5.0, "what is a chat bot", 130.0),  # other text and direction
                # the compiler question lost; a new utterance where there was none
                said(13.0, "is mark zuckerberg a robot", None), said(20.0, "thank you")]
    lines = diff(RECORDED, replayed)
    assert lines == [
        "~    1.00-2.50 s voice 'voice-1' -> 'Anna'",
        "~    5.00-6.50 s text 'what is a chatbot' -> 'what is a chat bot'; direction 90 deg -> 130 deg",
        "-    9.00-10.50 s recorded 'who invented the compiler': not in the replay",
        "~   13.00-14.50 s direction 355 deg -> none",
        "+   20.00-21.50 s replayed 'thank you': not in the recording",
        "diff: 4 recorded utterances, 4 replayed, 5 differences",
    ]

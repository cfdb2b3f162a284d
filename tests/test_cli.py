"""The launcher's own output: one readable line per fused result, progress on long files."""
from esiaf.cli import format_line, show_progress

ORIGIN_NS = 1_700_000_000_000_000_000


def fused(**extra):
    anchor = {"span": {"start_ns": ORIGIN_NS + 12_310_000_000, "end_ns": ORIGIN_NS + 14_050_000_000},
              "speech": {"hypotheses": [{"text": "go forward ten meters", "probability": 0.934}]}}
    return {"type": "fused_result", "id": 1, "revision": 1, "anchor": anchor, "results": {},
            "completion": "complete", "missing_components": [], **extra}


def test_a_fused_result_is_one_line_with_times_in_the_recording():
    assert format_line(fused(), ORIGIN_NS) == "[12.31–14.05 s] 'go forward ten meters' (p=0.93)"


def test_the_line_says_what_else_was_fused_how_it_completed_and_the_revision():
    line = format_line(fused(results={"ssl": [{}, {}]}, completion="timed_out", missing_components=["emotion"],
                             revision=2), ORIGIN_NS)
    assert line == ("[12.31–14.05 s] 'go forward ten meters' (p=0.93) ssl×2; timed_out, missing emotion rev 2")


class Client:
    def __init__(self, info):
        self.info = info

    def component(self, name):
        return {"name": name, "stats": {"info": self.info}}


def test_progress_on_long_files_only(capsys):
    show_progress(Client({"played_s": 40.2, "duration_s": 300.0}))
    show_progress(Client({"played_s": 10.0, "duration_s": 20.0}))
    assert capsys.readouterr().err == "esiaf: played 40 of 300 s (13 %)\n"


def test_direction_emotion_and_gender_are_on_the_line_with_their_shares():
    aggregates = {"ssl": {"azimuth_deg": 91.6}, "emotion": {"label": "angry", "probability": 0.814},
                  "gender": {"label": "female", "probability": 0.97}}
    results = {"ssl": [{}] * 12, "emotion": [{}], "gender": [{}]}
    assert format_line(fused(aggregates=aggregates, results=results), ORIGIN_NS) == \
        "[12.31–14.05 s] 'go forward ten meters' (p=0.93) from 92°, angry (0.81), female (0.97)"
    # an analyser that had nothing to say (too short) is simply absent; one that never answered is named
    line = format_line(fused(aggregates={"gender": {"label": "male", "probability": 0.5}},
                             results={"gender": [{}], "emotion": [], "ssl": []}, completion="timed_out",
                             missing_components=["emotion"]),
                       ORIGIN_NS)
    assert line == "[12.31–14.05 s] 'go forward ten meters' (p=0.93), male (0.50) timed_out, missing emotion"

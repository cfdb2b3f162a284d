"""Fusion engine units, no sockets: coverage, aggregates, timeouts and deadlines, revisions."""
from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest

from esiaf_services.orchestrator.fusion.aggregate import label_aggregate, overlaps, ssl_aggregate
from esiaf_services.orchestrator.fusion.coverage import GAP_TOLERANCE_NS, Coverage, StoredResult
from esiaf_services.orchestrator.fusion.engine import FusionEngine
from esiaf_services.orchestrator.fusion.latency import Latencies
from esiaf_services.orchestrator.fusion.orphans import Orphans, fuse_orphans, unanswered_segments
from esiaf_services.orchestrator.settings import FusionSettings, TimeoutSettings

MS = 1_000_000
S = 1000 * MS


def result(id_: int, component: str, type_: str, start: int, end: int, stream: str = "s", **payload) -> StoredResult:
    json = {"id": id_, "component": component, "type": type_, "stream_id": stream,
            "span": {"start_ns": start, "end_ns": end}, **payload}
    return StoredResult.from_json(json)


def direction(azimuth_deg: float, probability: float = 0.0) -> dict:
    return {"source_id": "", "azimuth_deg": azimuth_deg, "elevation_deg": 0.0,
            "probability": probability}


def test_coverage_is_contiguous_from_start_to_end_in_any_order():
    coverage = Coverage()
    coverage.add(2 * S, 3 * S)
    assert not coverage.covers(0, 3 * S)  # reaches the end, but from 2 s only
    coverage.add(0, S)
    assert not coverage.covers(0, 3 * S)  # a gap from 1 s to 2 s
    coverage.add(S + GAP_TOLERANCE_NS // 2, 2 * S)  # rounding of stamps is no gap
    assert coverage.covers(0, 3 * S) and coverage.starts == [0] and coverage.ends == [3 * S]
    assert not coverage.covers(0, 4 * S)
    coverage.forget_before(5 * S)
    assert coverage.starts == []


@pytest.mark.parametrize("span, inside", [((0, 10), True), ((20, 30), False), ((0, 5), False), ((12, 15), True),
                                          ((-5, 30), True), ((20, 20), True), ((30, 40), False)])
def test_overlap_means_sharing_time_and_touching_is_not_enough(span, inside):
    assert overlaps(*span, 5, 20) is inside


def test_ssl_aggregate_is_a_circular_mean_weighted_by_overlap():
    window = (0, 4 * S)
    results = [{"span": {"start_ns": 0, "end_ns": S}, "ssl": {"directions": [direction(350)]}},
               {"span": {"start_ns": S, "end_ns": 2 * S}, "ssl": {"directions": [direction(10)]}}]
    mean = ssl_aggregate(results, window)
    assert min(mean["azimuth_deg"], 360 - mean["azimuth_deg"]) < 1e-6  # not 180
    assert mean["concentration"] == pytest.approx(0.98481, abs=1e-4) and mean["overlap_s"] == 2.0
    # three times the overlap at 90°: pulled towards it
    results.append({"span": {"start_ns": S, "end_ns": 4 * S}, "ssl": {"directions": [direction(90)]}})
    assert ssl_aggregate(results, window)["azimuth_deg"] == pytest.approx(56.7136, abs=1e-3)
    # a direction's probability weighs too; outside the window weighs nothing
    weighted = ssl_aggregate([
        {"span": {"start_ns": 0, "end_ns": S}, "ssl": {"directions": [direction(0, 0.9), direction(90, 0.1)]}},
        {"span": {"start_ns": 5 * S, "end_ns": 6 * S}, "ssl": {"directions": [direction(180)]}}], (0, S))
    assert weighted["azimuth_deg"] == pytest.approx(6.3402, abs=1e-3)
    assert ssl_aggregate([{"span": {"start_ns": 0, "end_ns": S}, "ssl": {"directions": []}}], window) is None


def test_ssl_aggregate_is_the_talkers_track_not_the_loudspeakers():
    def frame(start, *directions):
        return {"span": {"start_ns": start * S, "end_ns": (start + 1) * S}, "ssl": {"directions": list(directions)}}

    def on(source_id, azimuth_deg, probability=0.5, background=False):
        return {**direction(azimuth_deg, probability), "source_id": source_id, "background": background}

    loudspeaker = [frame(t, on("s1", 20, 0.9, background=True)) for t in range(4)]  # louder, all along
    talker = [frame(1, on("s2", 90)), frame(2, on("s2", 94), on("s3", 200, 0.2))]  # and one stray peak
    aggregate = ssl_aggregate(loudspeaker + talker, (0, 4 * S))
    assert aggregate["source_id"] == "s2" and aggregate["azimuth_deg"] == pytest.approx(92, abs=0.01)
    assert aggregate["tracks"] == 3 and aggregate["directions"] == 2 and not aggregate["background"]
    # nothing but background: its direction, so marked
    only = ssl_aggregate(loudspeaker, (0, 4 * S))
    assert only["source_id"] == "s1" and only["background"] and only["azimuth_deg"] == pytest.approx(20)


def test_label_aggregate_is_an_overlap_weighted_distribution():
    results = [{"span": {"start_ns": 0, "end_ns": 3 * S},
                "emotion": {"label": "sad", "probability": 0.6,
                            "class_probabilities": {"sad": 0.6, "happy": 0.4}}},
               {"span": {"start_ns": 3 * S, "end_ns": 4 * S},
                "emotion": {"label": "happy", "probability": 0.9, "class_probabilities": {}}}]
    aggregate = label_aggregate(results, "emotion", (0, 4 * S))
    assert aggregate["distribution"] == {"happy": pytest.approx(0.55), "sad": pytest.approx(0.45)}
    assert aggregate["label"] == "happy" and list(aggregate["distribution"]) == ["happy", "sad"]


def test_a_voice_id_counts_as_its_label_and_the_rest_unknown_and_an_unknown_one_as_unknown():
    named = {"span": {"start_ns": 0, "end_ns": 1 * S},
             "voice_id": {"label": "Anna", "probability": 0.8, "class_probabilities": {"Anna": 0.9, "Ben": 0.7}}}
    gated = {"span": {"start_ns": 1 * S, "end_ns": 2 * S},  # under the voiceid's quality gate
             "voice_id": {"label": "unknown", "probability": 1.0, "class_probabilities": {},
                          "quality": {"snr_db": 3.0, "speech_s": 0.9, "reason": "speech 3 dB over the noise"}}}
    aggregate = label_aggregate([named, gated], "voice_id", (0, 2 * S))
    assert aggregate["distribution"] == {"unknown": pytest.approx(0.6), "Anna": pytest.approx(0.4)}
    assert label_aggregate([gated], "voice_id", (0, 2 * S))["distribution"] == {"unknown": pytest.approx(1.0)}


def test_timeouts_are_factor_times_running_mean_clamped_with_an_initial_value():
    latencies = Latencies(TimeoutSettings(factor=1.5, factors={"slow": 3.0}, initial_s=2.0,
                                          min_s=0.1, max_s=1.0, deviations=0))
    assert latencies.timeout_ns("ssl") == 2 * S
    for value in (100 * MS, 300 * MS):
        latencies.add("ssl", value)
        latencies.add("slow", value)
    assert latencies.timeout_ns("ssl") == 300 * MS  # 1.5 x 200 ms
    assert latencies.timeout_ns("slow") == 600 * MS
    latencies.add("fast", 1 * MS)
    latencies.add("late", 5 * S)
    assert latencies.timeout_ns("fast") == 100 * MS and latencies.timeout_ns("late") == S



def test_a_component_whose_latency_varies_is_granted_its_spread():
    """Steady at 200 ms: 1.5 x the mean. Then the machine is loaded and the latency jumps between
    200 ms and 1 s: the timeout follows the mean plus 4 mean deviations, so the slow answers are
    still waited for; steady again, it comes back down."""
    latencies = Latencies(TimeoutSettings(factor=1.5, min_s=0.05, max_s=10.0))
    for _ in range(20):
        latencies.add("voiceid", 200 * MS)
    assert latencies.timeout_ns("voiceid") == 300 * MS
    for value in (1000, 200, 1000, 200, 1000, 200):
        latencies.add("voiceid", value * MS)
    latency = latencies.by_component["voiceid"]
    loaded = latencies.timeout_ns("voiceid")
    assert loaded == int(latency.mean_ns + 4 * latency.deviation_ns) and loaded > 1000 * MS
    for _ in range(30):
        latencies.add("voiceid", 200 * MS)
    assert latencies.timeout_ns("voiceid") < 450 * MS

class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def engine_with(*components: tuple[str, str], **timeouts) -> tuple[FusionEngine, Clock]:
    ids = itertools.count(1)
    live = [SimpleNamespace(name=n, kind=d, stream_id="s") for n, d in components]
    clock = Clock()
    engine = FusionEngine([FusionSettings(name="u", anchor="speech", fuse=["ssl", "emotion"])],
                          allocate_id=lambda: next(ids), live_components=lambda: live,
                          timeouts=TimeoutSettings(**timeouts), clock_ns=clock)
    return engine, clock


def test_deadline_is_the_slowest_pending_components_own_and_dead_ones_are_not_waited_for():
    engine, clock = engine_with(("ssl", "ssl"), ("emo", "emotion"), ("emo2", "emotion"))
    engine.latencies.add("ssl", 100 * MS)   # timeout 150 ms
    engine.latencies.add("emo", 400 * MS)   # timeout 600 ms
    # emo2 unknown: initial 2 s
    assert engine.on_result(result(1, "asr", "speech", 0, S), S) == []
    assert engine.next_deadline_ns() == S + 2 * S
    assert engine.on_component_gone("emo2") == []
    assert engine.next_deadline_ns() == S + 600 * MS  # now the slowest is emo
    assert engine.on_result(result(2, "emo", "emotion", 0, S, nothing={"reason": "silence"}),
                            S + 10 * MS) == []
    assert engine.next_deadline_ns() == S + 150 * MS
    assert engine.on_timer(S + 149 * MS) == []
    clock.now = S + 150 * MS
    [fused] = engine.on_timer()
    assert fused.result.completion == "timed_out" and fused.revision == 1
    assert fused.result.model_dump()["missing"] == [{"component": "emo2", "type": "emotion", "reason": "gone"},
                                     {"component": "ssl", "type": "ssl", "reason": "timed_out"}]
    assert engine.next_deadline_ns() is None and not engine.open
    # late: revision 2, ssl no longer missing; a late `nothing` revises nothing
    [revised] = engine.on_result(result(3, "ssl", "ssl", 0, S, ssl={"directions": [direction(45)]}), 2 * S)
    assert revised.id == fused.id and revised.revision == 2
    assert [m.component for m in revised.result.missing] == ["emo2"]
    assert revised.result.aggregates["ssl"]["azimuth_deg"] == pytest.approx(45)
    assert engine.on_result(result(4, "emo2", "emotion", 0, S, nothing={"reason": "x"}), 2 * S) == []


def test_restored_pending_fusion_waits_for_the_same_deadline_or_publishes_when_covered():
    engine, clock = engine_with()
    engine.restore_result(result(1, "asr", "speech", 0, S, speech={"hypotheses": []}))
    engine.restore_result(result(2, "ssl", "ssl", 0, S, ssl={"directions": [direction(10)]}))
    settings = FusionSettings(name="u", anchor="speech", fuse=["ssl", "emotion"])
    anchor = result(1, "asr", "speech", 0, S, speech={"hypotheses": []})
    engine.restore_open(7, settings, anchor, {"ssl": ("ssl", 5 * S), "emo": ("emotion", 3 * S)})
    assert engine.next_deadline_ns() == 3 * S  # ssl covered before the restart
    clock.now = 3 * S
    [fused] = engine.on_timer()
    assert fused.id == 7 and fused.result.missing_components == ["emo"]
    assert [r["id"] for r in fused.result.results["ssl"]] == [2]


def test_a_component_that_ended_the_stream_is_not_waited_for_until_it_sends_again():
    engine, _ = engine_with(("ssl", "ssl"), ("emo", "emotion"))
    engine.on_result(result(1, "emo", "emotion", 0, 3 * S, nothing={"reason": "silence"}), S)
    assert engine.on_result(result(2, "asr", "speech", 0, S), S) == []  # waits for ssl
    [fused] = engine.on_end_of_stream("s", "ssl")
    assert fused.result.completion == "complete" and fused.result.missing == []
    [fused] = engine.on_result(result(3, "asr", "speech", S, 2 * S), 2 * S)  # not waited for
    assert fused.result.completion == "complete"
    engine.on_result(result(4, "ssl", "ssl", 0, S // 2, nothing={"reason": "none"}), 2 * S)
    assert engine.on_result(result(5, "asr", "speech", 2 * S, 3 * S), 3 * S) == []  # again


def test_late_results_within_the_revision_interval_make_one_revision():
    # 1,000 late results must not make 1,000 revisions (they made 400 MB of database once)
    engine, clock = engine_with(("ssl", "ssl"), revision_interval_s=0.5)
    clock.now = S
    engine.on_end_of_stream("s", "ssl")
    [first] = engine.on_result(result(1, "asr", "speech", 0, S), S)  # nothing to wait for
    assert first.revision == 1
    late = [engine.on_result(result(10 + i, "ssl2", "ssl", 0, S, ssl={"directions": [direction(90)]}),
                             S + (1 + i) * MS) for i in range(1000)]
    assert not any(late) and engine.next_deadline_ns() == S + 500 * MS
    assert engine.on_timer(S + 499 * MS) == []
    [revised] = engine.on_timer(S + 500 * MS)
    assert revised.revision == 2 and len(revised.result.results["ssl"]) == 200  # listed: bounded
    assert revised.result.omitted == {"ssl": 800}
    assert engine.next_deadline_ns() is None
    # a late result after the interval revises at once
    clock.now = S + 2 * S
    [third] = engine.on_result(result(5000, "ssl2", "ssl", 0, S, ssl={"directions": [direction(80)]}), 3 * S)
    assert third.revision == 3


def test_latencies_are_learnt_from_real_time_streams_only():
    """A --fast replay's capture times run ahead of the clock: its (negative) latencies must not set a
    later real-time run's timeouts; nor may a result from a clock that runs ahead."""
    engine, _ = engine_with(("asr", "speech"))
    engine.on_result(result(1, "asr", "nothing", 0, S), received_ns=S + 200 * MS)
    assert engine.latencies.by_component["asr"].mean_ns == 200 * MS
    engine.mark_replayed("s")
    engine.on_result(result(2, "asr", "nothing", 100 * S, 101 * S), received_ns=2 * S)  # 99 s "early"
    engine.on_result(result(3, "asr", "nothing", 102 * S, 103 * S), received_ns=2 * S)
    assert engine.latencies.by_component["asr"].count == 1
    engine.replayed.clear()
    engine.on_result(result(4, "asr", "nothing", 5 * S, 6 * S), received_ns=4 * S)  # a clock 2 s ahead
    assert engine.latencies.by_component["asr"].count == 1 and engine.latencies.by_component["asr"].mean_ns == 200 * MS


def test_a_capture_clock_3_s_behind_moves_deadlines_and_latencies_onto_ours():
    """Stream s is captured on a host whose clock is 3 s behind ours: its window ends 3 s later on
    our clock than its stamps say, so deadlines and latencies are measured from there."""
    ids = itertools.count(1)
    live = [SimpleNamespace(name="ssl", kind="ssl", stream_id="s")]
    engine = FusionEngine([FusionSettings(name="u", anchor="speech", fuse=["ssl"])], allocate_id=lambda: next(ids),
                          live_components=lambda: live, clock_ns=Clock(),
                          capture_offset_ns=lambda stream_id: 3 * S if stream_id == "s" else 0)
    engine.latencies.add("ssl", 100 * MS)  # timeout 150 ms
    assert engine.on_result(result(1, "asr", "speech", 0, S), received_ns=4 * S + 50 * MS) == []
    assert engine.next_deadline_ns() == 4 * S + 150 * MS  # not 1.15 s: long gone on our clock at arrival
    assert engine.latencies.by_component["asr"].mean_ns == 50 * MS  # not 3.05 s


def test_a_second_stream_waits_for_an_analyser_that_has_not_covered_it_yet():
    """A second stream's first fused result was `complete` with emotion null, because an
    analyser registered with another stream_id that had sent nothing for this one was assumed done."""
    engine, clock = engine_with(("emo", "emotion"))
    # emo registered with stream_id "s" and never sent anything for robot2: waited for
    assert engine.on_result(result(1, "asr", "speech", 0, S, stream="robot2"), S) == []
    emotion = result(2, "emo", "emotion", 0, S, stream="robot2", emotion={"label": "angry", "probability": 0.9})
    [fused] = engine.on_result(emotion, S + 10 * MS)
    assert fused.result.completion == "complete" and fused.result.results["emotion"][0]["id"] == 2
    clock.now = 10 * S
    # and one that never answers is reported missing, not assumed done
    assert engine.on_result(result(3, "asr", "speech", 2 * S, 3 * S, stream="robot3"), 3 * S) == []
    [timed_out] = engine.on_timer(10 * S)
    assert timed_out.result.completion == "timed_out" and timed_out.result.missing_components == ["emo"]


def test_segments_a_dead_recogniser_left_unanswered_are_fused_without_it_once():
    engine, clock = engine_with(("emo", "emotion"))
    vad = [result(10 + i, "vad", "vad", i * 3 * S, i * 3 * S + 2 * S, vad={"probability": 1.0}) for i in range(4)]
    engine.on_result(vad[0], 2 * S)
    assert engine.on_result(result(1, "asr", "speech", 0, 2 * S, speech={"hypotheses": [{"text": "hi"}]}),
                            2 * S) == []
    assert engine.open  # waiting for emo
    engine.on_result(result(2, "emo", "emotion", 0, 2 * S, emotion={"label": "angry"}), 2 * S)
    assert not engine.open
    for segment in vad[1:3]:  # the recogniser takes them, then dies before answering
        engine.on_result(segment, segment.end_ns)
    engine.on_result(result(3, "emo", "emotion", 3 * S, 5 * S, emotion={"label": "sad"}), 5 * S)
    assert [s.id for s in unanswered_segments(engine, "s", "asr")] == [11, 12]
    assert unanswered_segments(engine, "s", "emo") == [vad[2]]  # (emo answered the first two)
    clock.now = 9 * S
    [fused] = fuse_orphans(engine, "s", "asr", "speech", 9 * S)  # segment 11: emo has covered it
    assert fused.result.anchor["type"] == "vad" and fused.result.anchor["id"] == 11
    assert fused.result.completion == "components_gone"
    assert fused.result.model_dump()["missing"] == [{"component": "asr", "type": "speech", "reason": "gone"}]
    assert fused.result.aggregates["emotion"]["label"] == "sad"
    assert [f.anchor.id for f in engine.open.values()] == [12]  # waits for emo as any fusion does
    assert fuse_orphans(engine, "s", "asr", "speech", 9 * S) == []  # once: 11 published, 12 open
    [later] = engine.on_result(result(4, "emo", "emotion", 6 * S, 8 * S, emotion={"label": "sad"}), 10 * S)
    assert later.result.anchor["id"] == 12 and later.result.completion == "components_gone"
    assert fuse_orphans(engine, "s", "ssl", "ssl", 9 * S) == []  # no fusion is anchored on ssl


def test_segments_a_live_recogniser_passed_by_are_fused_without_it_when_it_answers_a_later_one_or_ends():
    """A recogniser that cannot keep up loses an utterance's audio and answers the next one: the
    segment between its two answers that it said nothing about is fused without it (reason
    ``skipped``) when the later answer comes; those after its last answer when it ends the stream."""
    engine, _ = engine_with()
    orphans = Orphans(engine)
    vad = [result(10 + i, "vad", "vad", i * 3 * S, i * 3 * S + 2 * S, vad={"probability": 1.0}) for i in range(5)]
    first = result(1, "asr", "speech", 0, 2 * S, speech={"hypotheses": [{"text": "hi"}]})
    engine.on_result(vad[0], 2 * S)
    assert orphans.before_result(first, 2 * S) == [] and len(engine.on_result(first, 2 * S)) == 1
    for segment in vad[1:3]:
        engine.on_result(segment, segment.end_ns)
    # segment 11 was passed by; segment 12 is answered, with `nothing`: an answer too
    answer = result(2, "asr", "speech", 6 * S, 8 * S, nothing={"reason": "no speech"})
    [skipped] = orphans.before_result(answer, 8 * S)
    engine.on_result(answer, 8 * S)
    assert skipped.result.anchor["type"] == "vad" and skipped.result.anchor["id"] == 11
    assert skipped.result.completion == "timed_out"
    assert skipped.result.model_dump()["missing"] == [{"component": "asr", "type": "speech", "reason": "skipped"}]
    assert orphans.before_result(result(3, "asr", "speech", 6 * S, 8 * S, nothing={"reason": "x"}), 8 * S) == []
    # results of a type no fusion anchors on, and a stream the recogniser never answered on, say nothing
    assert orphans.before_result(result(4, "ssl", "ssl", 9 * S, 10 * S, ssl={"azimuth_deg": 1.0}), 10 * S) == []
    engine.on_result(result(20, "vad", "vad", 0, 2 * S, stream="other", vad={"probability": 1.0}), 2 * S)
    assert orphans.before_result(result(5, "asr", "speech", 3 * S, 4 * S, stream="other",
                                        speech={"hypotheses": [{"text": "go"}]}), 4 * S) == []
    # the stream ends with two segments after its last answer: both fused, once
    for segment in vad[3:]:
        engine.on_result(segment, segment.end_ns)
    ended = orphans.on_end_of_stream("s", "asr", "speech", 15 * S)
    assert [f.result.anchor["id"] for f in ended] == [13, 14]
    assert orphans.on_end_of_stream("s", "asr", "speech", 16 * S) == []


def test_an_utterance_going_on_when_its_recogniser_died_is_fused_once_its_new_instance_says_nothing():
    engine, _ = engine_with()
    orphans = Orphans(engine)
    engine.on_result(result(10, "vad", "vad", 0, 2 * S, vad={"probability": 1.0}), 2 * S)
    engine.on_result(result(1, "asr", "speech", 0, 2 * S, speech={"hypotheses": [{"text": "hi"}]}), 2 * S)
    assert orphans.on_death("s", "asr", "speech", 5 * S, 5 * S) == []  # nothing unanswered yet
    # the utterance [4 s, 7 s] was going on: its segment ends, its new instance joined it late
    engine.on_result(result(11, "vad", "vad", 4 * S, 7 * S, vad={"probability": 1.0}), 7 * S)
    late = result(2, "asr", "speech", 4 * S, 7 * S, nothing={"reason": "joined the utterance 1000 ms after its start"})
    assert engine.on_result(late, 7 * S) == []  # a `nothing` opens no fusion of its own
    [fused] = orphans.on_result(late, 7 * S)
    assert fused.result.anchor["id"] == 11 and fused.result.completion == "components_gone"
    assert fused.result.model_dump()["missing"] == [{"component": "asr", "type": "speech", "reason": "gone"}]
    # the next utterance, begun after the death, ends the watch: a later `nothing` is only that
    nxt = result(3, "asr", "speech", 9 * S, 10 * S, speech={"hypotheses": [{"text": "go"}]})
    assert orphans.on_result(nxt, 10 * S) == [] and not orphans.watched
    assert orphans.on_result(result(4, "asr", "speech", 4 * S, 7 * S, nothing={"reason": "x"}), 11 * S) == []


def test_a_recogniser_that_comes_back_revises_what_was_fused_without_it_and_never_doubles_it():
    """Its instance was declared dead (frozen 20 s): what it left unanswered is fused without it, and so is
    each segment that comes while no instance of it lives; its answers, when it comes back, are those
    fused results' next revisions (anchored on the answer), not new fused results."""
    engine, _ = engine_with(("emo", "emotion"))
    orphans = Orphans(engine)
    vad = [result(10 + i, "vad", "vad", i * 3 * S, i * 3 * S + 2 * S, vad={"probability": 1.0}) for i in range(3)]
    for i, segment in enumerate(vad[:2]):
        engine.on_result(segment, segment.end_ns)
        engine.on_result(result(20 + i, "emo", "emotion", segment.start_ns, segment.end_ns,
                                emotion={"label": "sad"}), segment.end_ns)
    at_death = orphans.on_death("s", "asr", "speech", 6 * S, 6 * S)
    assert [f.result.model_dump()["anchor"]["id"] for f in at_death] == [10, 11]
    engine.on_result(result(22, "emo", "emotion", 6 * S, 8 * S, emotion={"label": "sad"}), 8 * S)
    engine.on_result(vad[2], 8 * S)
    assert orphans.on_segment(vad[2], 8 * S, alive=lambda service: True) == []  # another instance answers it
    [meanwhile] = orphans.on_segment(vad[2], 8 * S, alive=lambda service: False)  # none: nobody will
    assert meanwhile.result.model_dump()["missing"] == [{"component": "asr", "type": "speech", "reason": "gone"}]
    assert orphans.on_segment(vad[2], 8 * S, alive=lambda service: False) == []  # once
    fused_ids = {f.id for f in [*at_death, meanwhile]}
    for i, segment in enumerate(vad):  # it comes back and answers all three, late
        answer = result(30 + i, "asr", "speech", segment.start_ns, segment.end_ns,
                        speech={"hypotheses": [{"text": f"question {i}"}]})
        assert orphans.before_result(answer, (30 + i) * S) == []
        [revised] = [f for f in engine.on_result(answer, (30 + i) * S) if f.revision > 1]
        assert revised.id in fused_ids and revised.result.model_dump()["anchor"]["id"] == 30 + i
        assert revised.result.model_dump()["missing"] == [] and revised.result.model_dump()["results"]["emotion"]
    assert not engine.open and len({f.id for f in engine.streams["s"].published.overlapping(0, 10 * S)}) == 3


def test_an_utterance_broken_off_by_its_vads_death_is_fused_as_lost_once():
    """The vad dies mid-utterance: the recogniser's `nothing` over what it heard of it ("utterance broken
    off") is fused, anchored on itself, with the vad missing; a later utterance ends the watch."""
    engine, _ = engine_with()
    orphans = Orphans(engine)
    assert orphans.on_death("s", "vad", "vad", 3 * S, 3 * S) == []
    broken = result(1, "asr", "speech", 1 * S, 2 * S, nothing={"reason": "utterance broken off: its VAD went away"})
    engine.on_result(broken, 6 * S)
    [lost] = orphans.on_result(broken, 6 * S)
    anchor = lost.result.anchor
    assert anchor["id"] == 1 and anchor["nothing"]["reason"].startswith("utterance broken")
    assert lost.result.model_dump()["missing"] == [{"component": "vad", "type": "vad", "reason": "gone"}]
    nxt = result(2, "asr", "speech", 5 * S, 6 * S, speech={"hypotheses": [{"text": "go"}]})
    assert orphans.on_result(nxt, 7 * S) == [] and not orphans.segmenters_gone
    assert orphans.on_result(result(3, "asr", "speech", 1 * S, 2 * S, nothing={"reason": "x"}), 8 * S) == []


def test_a_replays_player_far_ahead_of_the_microphones_does_not_make_fusion_forget_what_it_plays():
    """A player replaying a long robot voice reports its parts minutes before the microphones reach them."""
    engine, clock = engine_with(("asr", "speech"))
    parts = [result(100 + n, "player", "playback", n * 10 * S, (n * 10 + 8) * S,
                    playback={"text": "", "attributes": {"item": 1, "part": n}}) for n in range(100)]
    for part in parts:  # 1000 s of parts, all reported at once, far more than memory_s (120 s) ahead
        engine.on_result(part, 0)
    clock.now = 73 * S
    fused, = engine.on_result(result(1, "asr", "speech", 71 * S, 73 * S, speech={"hypotheses": []}), 73 * S)
    assert fused.result.playback_overlap == 1.0 and fused.result.source == "robot"


def test_a_late_utterance_of_a_replay_still_finds_what_the_robot_played():
    """In a replay (--fast) the localiser runs minutes ahead of the recogniser: the utterance the recogniser
    answers 150 s behind the localiser still finds the robot's playback in its span (it found none, 2026-11-28:
    the localiser's results had moved fusion's memory past it)."""
    engine, clock = engine_with(("asr", "speech"), ("ssl", "ssl"))
    for n in range(30):  # the robot plays 8 s of every 10, reported ahead
        engine.on_result(result(1000 + n, "player", "playback", n * 10 * S, (n * 10 + 8) * S,
                                playback={"text": "", "attributes": {"item": 1, "part": n}}), 0)
    engine.on_result(result(1, "asr", "speech", 0, 1 * S, speech={"hypotheses": []}), S)
    for n in range(300 * 4):  # the localiser 300 s on
        engine.on_result(result(2000 + n, "ssl", "ssl", n * S // 4, (n + 1) * S // 4,
                                ssl={"directions": [direction(20)]}), n * S // 4)
    clock.now = 300 * S
    fused, = engine.on_result(result(2, "asr", "speech", 151 * S, 153 * S, speech={"hypotheses": []}), 300 * S)
    assert fused.result.playback_overlap == 1.0 and fused.result.source == "robot"


def test_a_late_utterance_of_a_replay_still_finds_its_direction():
    """In a replay (--fast) the localiser runs minutes ahead of the recogniser: an utterance the recogniser
    answers 150 s behind it is fused with the localiser's directions over its span, complete (the
    localiser's results and coverage had been forgotten 120 s behind the newest, 2026-11-28: no direction)."""
    engine, clock = engine_with(("asr", "speech"), ("ssl", "ssl"))
    engine.on_result(result(1, "asr", "speech", 0, 1 * S, speech={"hypotheses": []}), S)
    for n in range(300 * 4):  # the localiser 300 s on
        engine.on_result(result(2000 + n, "ssl", "ssl", n * S // 4, (n + 1) * S // 4,
                                ssl={"directions": [direction(40 if 150 <= n // 4 < 154 else 200)]}), n * S // 4)
    clock.now = 300 * S
    fused, = engine.on_result(result(2, "asr", "speech", 151 * S, 153 * S, speech={"hypotheses": []}), 300 * S)
    assert fused.result.completion == "complete" and fused.result.missing == []
    assert fused.result.aggregates["ssl"]["azimuth_deg"] == pytest.approx(40)

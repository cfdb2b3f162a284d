"""Unit tests, no sockets: codec, fusion engine, registry, stream ends, hub, store."""
from __future__ import annotations

import asyncio
import itertools
import json
import sqlite3

import pytest

from esiaf.control_messages import State
from esiaf.proto import esiaf_pb2 as pb
from esiaf_services.orchestrator.fusion.engine import FusionEngine, StoredResult
from esiaf_services.orchestrator.planes.codec import BadResult, parse_result, result_to_json
from esiaf_services.orchestrator.planes.hub import Hub, Outgoing
from esiaf_services.orchestrator.registry.components import InstanceConflict, Registry, TopicConflict
from esiaf_services.orchestrator.registry.streams import StreamEnds
from esiaf_services.orchestrator.settings import FusionSettings, OrchestratorSettings
from esiaf_services.orchestrator.store.database import MIGRATIONS, Store, StoreError

BIG_NS = 1_763_720_001_850_000_123
FMT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


# codec
def test_result_json_keeps_int64_as_integers_and_has_one_payload_key():
    result = pb.Result(component="emo", type=pb.RESULT_TYPE_EMOTION, stream_id="s",
                       produced_ns=BIG_NS + 5, sequence=7)
    result.span.start_ns, result.span.end_ns = BIG_NS - 1000, BIG_NS
    result.emotion.label = "happy"
    result.emotion.class_probabilities["happy"] = 0.75
    parsed = parse_result(result.SerializeToString())
    as_json = json.loads(json.dumps(result_to_json(parsed, 3, BIG_NS + 2_500_000)))
    assert as_json == {"id": 3, "component": "emo", "instance": "", "type": "emotion", "stream_id": "s",
                       "span": {"start_ns": BIG_NS - 1000, "end_ns": BIG_NS},
                       "produced_ns": BIG_NS + 5, "received_ns": BIG_NS + 2_500_000,
                       "latency_ms": 2.5, "sequence": 7,
                       "emotion": {"label": "happy", "probability": 0.0,
                                   "class_probabilities": {"happy": 0.75}, "embedding": [],
                                   # voice_id's quality: every field is given, all zero for other kinds
                                   "quality": {"snr_db": 0.0, "speech_s": 0.0, "reason": ""}}}


def test_nothing_payload_fits_any_type():
    result = pb.Result(component="ssl", type=pb.RESULT_TYPE_SSL)
    result.nothing.reason = "no source"
    as_json = result_to_json(parse_result(result.SerializeToString()), 1, 0)
    assert as_json["nothing"] == {"reason": "no source"} and "ssl" not in as_json


@pytest.mark.parametrize("result, complaint", [
    (pb.Result(component="x", type=pb.RESULT_TYPE_VAD), "no payload"),
    (pb.Result(component="x", vad=pb.VadResult(probability=1)), "no valid type"),
    (pb.Result(component="x", type=pb.RESULT_TYPE_SPEECH, vad=pb.VadResult()), "vad payload"),
    (pb.Result(type=pb.RESULT_TYPE_VAD, vad=pb.VadResult()), "without a component"),
    (pb.Result(component="x", type=pb.RESULT_TYPE_VAD, vad=pb.VadResult(),
               span=pb.Span(start_ns=2, end_ns=1)), "ends before it starts"),
])
def test_bad_results_are_refused_with_a_reason(result, complaint):
    with pytest.raises(BadResult, match=complaint):
        parse_result(result.SerializeToString())


# fusion
def stored(type_: str = "speech", stream: str = "default", result_id: int = 1) -> StoredResult:
    return StoredResult(id=result_id, component="asr", type=type_, stream_id=stream,
                        start_ns=10, end_ns=20, json={"id": result_id})


def test_anchor_only_fusions_publish_each_matching_anchor_at_once():
    ids = itertools.count(1)
    engine = FusionEngine([FusionSettings(name="speech", anchor="speech"),
                           FusionSettings(name="robot1", anchor="speech", stream="r1"),
                           FusionSettings(name="vad", anchor="vad")],
                          allocate_id=lambda: next(ids), clock_ns=lambda: 99)
    fused = engine.on_result(stored(stream="r1"), 30)
    assert [(f.fusion, f.id, f.revision) for f in fused] == [("speech", 1, 1), ("robot1", 2, 1)]
    assert fused[0].result.model_dump() == {
        "type": "fused_result", "id": 1, "revision": 1, "fusion": "speech", "stream_id": "r1", "anchor": {"id": 1},
        "results": {}, "aggregates": {}, "completion": "complete", "missing_components": [], "missing": [],
        "published_ns": 99, "playback_overlap": 0.0, "source": "person", "seq": 0,
        "omitted": {}}  # numbered when stored
    assert [f.fusion for f in engine.on_result(stored(stream="r2", result_id=2), 30)] == ["speech"]
    assert [f.fusion for f in engine.on_result(stored(type_="vad", result_id=3), 30)] == ["vad"]
    assert engine.on_result(stored(type_="gender", result_id=4), 30) == []


def test_a_covered_nothing_result_anchors_no_fusion():
    engine = FusionEngine([FusionSettings(name="speech", anchor="speech")], allocate_id=lambda: 1)
    nothing = StoredResult(id=1, component="asr", type="speech", stream_id="s", start_ns=10, end_ns=20,
                           json={"id": 1, "nothing": {"reason": "no words recognised"}})
    assert engine.on_result(nothing, 30) == []


def test_settings_refuse_bad_kind_names_and_duplicate_fusions():
    with pytest.raises(ValueError, match="anchor"):
        OrchestratorSettings(fusions=[{"name": "x", "anchor": "Speech!"}])  # any name like "rate" is a kind
    with pytest.raises(ValueError, match="unique"):
        OrchestratorSettings(fusions=[{"name": "x", "anchor": "speech"},
                                      {"name": "x", "anchor": "vad"}])


# registry
def register(registry: Registry, name: str, inputs=(), outputs=(), fmt=FMT, instance=None, incarnation=None):
    component, _ = registry.register(
        name=name, kind="other", stream_id="default",
        inputs={t: fmt for t in inputs}, outputs={t: fmt for t in outputs},
        audio_endpoint=f"tcp://{name}:1" if outputs else None, host="", pid=None, info={},
        instance=instance, incarnation=incarnation)
    return component


def test_registry_pushes_only_changed_states():
    registry = Registry()
    vad = register(registry, "vad", inputs=["raw"])
    asr = register(registry, "asr", inputs=["speech"])
    assert registry.changed_states() == []
    grabber = register(registry, "grabber", outputs=["raw"], fmt={**FMT, "sample_rate_hz": 48000})
    changed = registry.changed_states()
    assert [c.name for c, _ in changed] == ["vad"]  # asr's peers and formats did not change
    assert changed[0][1].peers == {"raw": ["tcp://grabber:1"]}
    assert changed[0][1].formats["raw"]["sample_rate_hz"] == 16000  # a tie: the cheaper
    registry.remove(grabber.component_id)
    assert registry.changed_states() == [(vad, State(peers={"raw": []}, formats={"raw": FMT}))]
    assert asr.status == "alive"


def test_registry_conflict_leaves_old_instance_in_place():
    registry = Registry()
    register(registry, "grabber", outputs=["raw"])
    old = register(registry, "vad", inputs=["raw"])
    with pytest.raises(TopicConflict, match="'raw'"):
        register(registry, "vad", inputs=["raw"], fmt={**FMT, "channels": 4})
    assert registry.instances("vad") == [old]
    # its own old declaration does not conflict when the same process registers again
    solo = Registry()
    first = register(solo, "mic", outputs=["raw"], fmt={**FMT, "channels": 2}, instance="mic-1", incarnation="a")
    second = register(solo, "mic", outputs=["raw"], fmt=FMT, instance="mic-1", incarnation="a")
    assert first.status == "replaced" and solo.live == {"mic-1": second} and not solo.departed


def test_a_name_registered_again_is_another_instance_and_a_live_instance_id_is_refused():
    registry = Registry()
    first = register(registry, "asr", inputs=["speech"], instance="asr-a", incarnation="p1")
    second = register(registry, "asr", inputs=["speech"])  # no id given: one is made up
    assert registry.instances("asr") == [first, second] and first.status == second.status == "alive"
    for incarnation in ("p2", None):  # another process, or one that cannot say it is the same
        with pytest.raises(InstanceConflict, match="'asr-a' is held by a live instance"):
            register(registry, "asr", inputs=["speech"], instance="asr-a", incarnation=incarnation)
    assert registry.get("asr-a") is first
    registry.expire(2.5, now_mono=first.last_seen_mono + 3)  # declared dead: its id is free again
    third = register(registry, "asr", inputs=["speech"], instance="asr-a", incarnation="p2")
    assert registry.get("asr-a") is third and "asr-a" not in registry.departed


def test_a_producers_state_names_the_live_consumers_of_its_outputs():
    """The only subscribers a producer's audio output takes (esiaf/gate.py): who consumes its topics, now."""
    registry = Registry()
    grabber = register(registry, "grabber", outputs=["raw"])
    assert registry.state_of(grabber).consumers == []
    vad = register(registry, "vad", inputs=["raw"], outputs=["speech"])
    a = register(registry, "asr", inputs=["speech"], instance="asr-a")
    b = register(registry, "asr", inputs=["speech"], instance="asr-b")
    assert registry.state_of(grabber).consumers == [vad.component_id]
    assert registry.state_of(vad).consumers == ["asr-a", "asr-b"]
    assert registry.state_of(a).consumers is None  # no outputs
    registry.declare_dead(b.component_id)
    assert registry.state_of(vad).consumers == ["asr-a"]


def test_replicas_share_the_streams_sticky_and_balanced_and_a_dead_ones_move_at_once():
    registry = Registry()
    vad = register(registry, "vad", inputs=["raw"], outputs=["speech"])
    a = register(registry, "asr", inputs=["speech"], instance="asr-a")
    for stream in ("s1", "s2"):
        registry.add_stream(stream)
    assert registry.state_of(a).streams is None and registry.state_of(vad).streams is None  # alone: all
    b = register(registry, "asr", inputs=["speech"], instance="asr-b")
    assert registry.state_of(a).streams == ["s1", "s2"] and registry.state_of(b).streams == []  # sticky
    for stream in ("s3", "s4", "s5"):
        registry.add_stream(stream)
    assert registry.state_of(b).streams == ["s3", "s4"]  # the least loaded
    assert registry.state_of(a).streams == ["s1", "s2", "s5"]  # the older on a tie
    assert registry.state_of(vad).streams is None
    registry.end_stream("s1")
    registry.add_stream("s6")
    assert registry.state_of(a).streams == ["s2", "s5", "s6"]
    registry.expire(2.5, now_mono=max(a.last_seen_mono, b.last_seen_mono) + 3)
    assert registry.live == {}
    c = register(registry, "asr", inputs=["speech"], instance="asr-c")
    d = register(registry, "asr", inputs=["speech"], instance="asr-d")
    registry.remove("asr-c")  # left: its streams go to the survivor
    assert registry.state_of(d).streams is None and registry.assignments.serving("asr") == {
        s: "asr-d" for s in ("s2", "s3", "s4", "s5", "s6")}
    assert c.status == "alive"  # a clean leave is not a death


def test_a_stream_first_heard_from_a_replica_stays_with_it():
    registry = Registry()
    a = register(registry, "asr", inputs=["speech"], instance="asr-a")
    b = register(registry, "asr", inputs=["speech"], instance="asr-b")
    assert registry.add_stream("x", served_by=b)
    assert registry.state_of(b).streams == ["x"] and registry.state_of(a).streams == []
    assert not registry.add_stream("x", served_by=a)  # known already: it stays


def test_a_heartbeats_state_is_computed_again_after_every_change_and_only_then():
    """offer_current() (what every heartbeat does) keeps the last state until the registry changed;
    after each change below, each live component is offered the state state_of() gives now."""
    registry = Registry()
    computed = []
    state_of = registry.state_of
    registry.state_of = lambda component, formats=None: computed.append(component) or state_of(component, formats)
    vad = register(registry, "vad", inputs=["raw"], outputs=["speech"])
    a = register(registry, "asr", inputs=["speech"], instance="asr-a")
    changes = [lambda: register(registry, "asr", inputs=["speech"], instance="asr-b"),
               lambda: registry.add_stream("s1"), lambda: registry.add_stream("s2", served_by=a),
               lambda: registry.end_stream("s1"), lambda: registry.remove("asr-b"),
               lambda: register(registry, "mic", outputs=["raw"]), lambda: registry.declare_dead(vad.component_id)]
    for change in changes:
        before = set(registry.live)
        change()
        # once each after the change (one that registered just now got it then); not again
        for expected_computed in (before & set(registry.live), set()):
            computed.clear()
            for component in registry.live.values():
                registry.offer_current(component)
                assert component.pushed_state == state_of(component)
            assert {c.component_id for c in computed} == expected_computed
    assert a.pushed_state is not None and a.pushed_state.peers == {"speech": []}  # the vad died
    # registered; b came (streams: none), s1 given to it, s2 too, s1 ended, b left (all again), vad died
    assert a.state_version == 7


def test_registry_expires_silent_components():
    registry = Registry()
    component = register(registry, "vad", inputs=["raw"])
    assert registry.expire(2.5, now_mono=component.last_seen_mono + 2.4) == []
    assert registry.expire(2.5, now_mono=component.last_seen_mono + 2.6) == [component]
    assert component.status == "dead" and registry.all(include_departed=True) == [component]


# stream ends
def test_stream_ends_when_every_awaited_service_said_so():
    ends = StreamEnds()
    ends.on_end_of_stream("s", "vad")
    assert ends.finished({"vad", "asr"}) == []
    ends.on_end_of_stream("s", "asr")
    assert ends.finished({"vad", "asr"}) == ["s"]
    assert ends.finished({"vad", "asr"}) == []  # once
    ends.on_end_of_stream("s", "vad")  # late: ignored, the stream has ended
    ends.on_result("s")  # starts it again
    ends.on_end_of_stream("s", "vad")
    assert ends.finished({"vad", "asr"}) == []
    assert ends.finished({"vad"}) == ["s"]  # asr died: nobody else to wait for


# hub
def test_slow_client_is_dropped_without_blocking_others():
    async def scenario():
        hub = Hub(max_queue=3)
        slow = hub.subscribe("slow")
        fast = hub.subscribe("fast", stream="s")
        other = hub.subscribe("other-stream", stream="t")
        for i in range(4):
            hub.publish(Outgoing(text=str(i), stream_id="s", fusion="speech", fused_id=i))
            if not fast.queue.empty():
                fast.queue.get_nowait()  # the fast client keeps up
        return hub, slow, fast, other

    hub, slow, fast, other = asyncio.run(scenario())
    assert slow.dropped.is_set() and "too slow" in slow.close_reason and slow.queue.empty()
    assert not fast.dropped.is_set() and len(hub) == 2 and hub.dropped_clients == 1
    assert other.queue.empty()


# store
def test_store_migrates_and_refuses_newer_schema(tmp_path):
    path = tmp_path / "esiaf.db"
    Store(path).close()
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == len(MIGRATIONS)
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        db.execute(f"PRAGMA user_version = {len(MIGRATIONS) + 1}")
    with pytest.raises(StoreError, match="newer"):
        Store(path)
    Store(path, fresh=True).close()  # --fresh starts again


def test_store_returns_latest_revision_of_each_fused_result(tmp_path):
    store = Store(tmp_path / "esiaf.db")
    store.begin()
    for revision, text in ((1, '{"r":1}'), (2, '{"r":2}')):
        store.add_fused(fused_id=1, revision=revision, fusion="f", stream_id="s", start_ns=0,
                        end_ns=5, published_ns=revision, json_text=text)
    store.commit()
    page = store.query_fused()
    assert page.items == ['{"r":2}'] and page.revisions == {1: 2}
    assert page.to_json() == '{"items":[{"r":2}],"next_after_id":1}'
    store.close()

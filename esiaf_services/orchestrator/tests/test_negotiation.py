"""Format negotiation: the strategies (the thesis' cases), recomputation, pushes only on change."""
from __future__ import annotations

import pytest

from esiaf.settings import SettingsError
from esiaf_services.orchestrator.registry.negotiation import Declaration, choose, conversions
from esiaf_services.orchestrator.settings import load
from esiaf_services.orchestrator.tests.helpers import FMT16, component_body

FMT48 = {**FMT16, "sample_rate_hz": 48000}
FMT16_FLOAT = {**FMT16, "sample_type": "float32"}
FMT16_UNSIGNED = {**FMT16, "sample_type": "uint16"}
FMT16_BIG = {**FMT16, "endianness": "big"}


def declared(producers: list[dict], consumers: list[dict]) -> list[Declaration]:
    # every format a fresh dict: formats are compared by value, never by identity
    return ([Declaration(f"p{i}", "producer", dict(f)) for i, f in enumerate(producers)]
            + [Declaration(f"c{i}", "consumer", dict(f)) for i, f in enumerate(consumers)])


def test_one_16k_producer_four_48k_consumers():
    topic = declared([FMT16], [FMT48] * 4)
    assert choose(topic, "min_conversions") == FMT48  # 1 conversion instead of 4
    assert conversions(topic, FMT48) == 1 and conversions(topic, FMT16) == 4
    assert choose(topic, "min_bandwidth") == FMT16  # 256 kbit/s instead of 768


@pytest.mark.parametrize("producers, consumers, strategy, expected", [
    # one conversion either way: the cheaper format
    ([FMT48], [FMT16], "min_conversions", FMT16),
    ([FMT16], [FMT48], "min_conversions", FMT16),
    # 16 kHz float32 (512 kbit/s) is cheaper than 48 kHz int16 (768 kbit/s)
    ([FMT48], [FMT16_FLOAT], "min_conversions", FMT16_FLOAT),
    # the same bandwidth: the fewer conversions
    ([FMT16_UNSIGNED], [FMT16, FMT16], "min_bandwidth", FMT16),
    ([FMT16, FMT16_UNSIGNED], [FMT16_UNSIGNED], "min_bandwidth", FMT16_UNSIGNED),
    # the same conversions and bandwidth: the producer's format
    ([FMT16_BIG], [FMT16], "min_conversions", FMT16_BIG),
    ([FMT16_BIG], [FMT16], "min_bandwidth", FMT16_BIG),
])
def test_ties(producers, consumers, strategy, expected):
    assert choose(declared(producers, consumers), strategy) == expected


def test_a_full_tie_keeps_the_current_format():
    topic = declared([FMT16, FMT16_BIG], [])
    assert choose(topic, "min_conversions") == FMT16  # the first producer's
    assert choose(topic, "min_conversions", current=FMT16_BIG) == FMT16_BIG  # no needless switch


def test_min_conversions_is_not_min_bandwidth_in_disguise():
    """The original compared formats by identity, so every candidate tied and it fell back to the
    cheapest. Three consumers in one expensive format outvote one cheap producer."""
    topic = declared([FMT16], [FMT48, FMT48, FMT16_FLOAT])
    assert choose(topic, "min_conversions") == FMT48
    assert choose(topic, "min_bandwidth") == FMT16


def test_strategy_is_a_setting_refused_when_unknown():
    assert load(env={}).format_strategy == "min_conversions"
    assert load(env={"ESIAF_ORCHESTRATOR_FORMAT_STRATEGY": "min_bandwidth"}).format_strategy == "min_bandwidth"
    with pytest.raises(SettingsError, match="format_strategy"):
        load(env={"ESIAF_ORCHESTRATOR_FORMAT_STRATEGY": "fastest"})


def formats_pushed(fake) -> list[dict]:
    """The formats of every state message waiting on the fake's socket (no heartbeat sent) that
    differ from the formats it was told before. A producer is also told its consumers, so a
    consumer's arrival pushes it a state whose formats may be the same."""
    pushed = []
    while (message := fake.recv(timeout_s=0.3)) is not None:
        if message["formats"] != fake.told_formats:
            pushed.append(message["formats"])
            fake.told_formats = message["formats"]
    return pushed


def connected(fake):
    """Heartbeats once and takes the answer: the ROUTER now knows the fake's socket."""
    fake.heartbeat()
    answer = fake.recv()
    assert answer is not None
    fake.told_formats = answer["formats"]
    return fake


@pytest.mark.parametrize("strategy, after_second", [("min_conversions", FMT48), ("min_bandwidth", FMT16)])
def test_recomputed_on_registration_and_pushed_only_where_it_changed(make_orchestrator, zctx, strategy,
                                                                      after_second):
    import httpx

    from esiaf_services.orchestrator.tests.helpers import FakeComponent
    orch = make_orchestrator(format_strategy=strategy)
    with httpx.Client(base_url=orch.url, timeout=5.0) as http:
        def fake(name, **kwargs):
            return connected(FakeComponent(zctx, http, component_body(name, **kwargs)))

        producer = fake("mic", outputs=["raw"], fmt=FMT16)
        bystander = fake("other", inputs=["elsewhere"], fmt=FMT48)
        first = fake("asr1", inputs=["raw"], fmt=FMT48)
        assert first.registration["formats"] == {"raw": FMT16}  # a tie: the cheaper
        assert formats_pushed(producer) == []  # nothing changed for it
        second = fake("asr2", inputs=["raw"], fmt=FMT48)
        assert second.registration["formats"] == {"raw": after_second}
        if after_second == FMT48:  # the switch is pushed to those already there, once
            assert formats_pushed(producer) == [{"raw": FMT48}]
            assert formats_pushed(first) == [{"raw": FMT48}]
        else:
            assert formats_pushed(producer) == formats_pushed(first) == []
        assert formats_pushed(bystander) == []
        topic = http.get("/topics").json()["items"]
        raw = next(t for t in topic if t["topic"] == "raw")
        assert raw["format"] == after_second and raw["conversions"] == (1 if after_second == FMT48 else 2)
        for component in (producer, bystander, first, second):
            component.close()


def test_a_topic_whose_only_consumer_leaves_or_dies_goes_back_to_its_producers_format(orch, http, component):
    producer = connected(component("mic", outputs=["raw"], fmt=FMT48))
    consumer = connected(component("asr", inputs=["raw"], fmt=FMT16))
    assert consumer.registration["formats"] == {"raw": FMT16}
    assert formats_pushed(producer) == [{"raw": FMT16}]  # it now converts 48 -> 16 kHz
    assert http.delete(f"/components/{consumer.id}").status_code == 204
    assert formats_pushed(producer) == [{"raw": FMT48}]  # nobody wants 16 kHz any more
    # a death (silence) recomputes too
    dying = connected(component("asr2", inputs=["raw"], fmt=FMT16))
    assert dying.registration["formats"] == {"raw": FMT16}
    pushed = producer.wait_for(lambda m: m["formats"] == {"raw": FMT48}, timeout_s=8, heartbeat_every_s=0.5)
    assert pushed["formats"] == {"raw": FMT48}
    assert next(c for c in http.get("/components", params={"include_dead": "true"}).json()["items"]
                if c["name"] == "asr2")["status"] == "dead"

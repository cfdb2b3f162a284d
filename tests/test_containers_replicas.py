"""Containers: replicas of the recogniser under compose (--scale asr=3) sharing the streams, one
killed and one cut off the network. Same needs and skips as tests/test_containers.py."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import soundfile
from container_kit import (
    EXAMPLE,
    TRUTH,
    at_least,
    best_text,
    run,
)

from esiaf.tools.testing import normalise, poll

pytestmark = [pytest.mark.containers, pytest.mark.timeout(3600)]  # the first one builds the images


class Replicated:
    """A compose project with ``asr`` instances of the recogniser, no grabber, emotion, gender or
    voiceid: grabbers are started one by one, each with a stream of its own, playing the example
    ``copies`` times over."""

    def __init__(self, project, tmp_path: Path, asr: int, copies: int):
        samples, rate = soundfile.read(EXAMPLE, dtype="int16")
        longer = tmp_path / f"example-x{copies}.wav"
        soundfile.write(longer, np.concatenate([samples] * copies), rate)
        self.p = p = project(longer)
        p.env.update(ESIAF_GRABBER_REPLICAS="0", ESIAF_EMOTION_REPLICAS="0", ESIAF_GENDER_REPLICAS="0",
                     ESIAF_VOICEID_REPLICAS="0")
        p("up", "-d", "--scale", f"asr={asr}", timeout=600)
        poll(lambda: len(self.services().get("asr", {}).get("instances", [])) == asr, timeout_s=120)

    def services(self) -> dict:
        return self.p.http.get("/components").json()["services"]

    def fused(self, stream: str) -> list[dict]:
        return self.p.http.get("/fused", params={"stream": stream, "limit": 100}).json()["items"]

    def grabber(self, stream: str) -> None:
        """A one-off container of the grabber service, playing its stream."""
        self.p("run", "-d", "-e", f"ESIAF_STREAM_ID={stream}", "grabber")


def test_three_asr_replicas_share_six_streams_each_utterance_decoded_once_and_a_killed_ones_move(project, tmp_path):
    """`--scale asr=3`: six grabbers, each its own stream, against three asr instances. Each
    stream is served by one instance, every sentence is decoded once; a killed instance's streams
    move to the survivors, which decode their next sentences."""
    r = Replicated(project, tmp_path, asr=3, copies=2)  # 42 s, 10 sentences: room to kill
    p, services, fused = r.p, r.services, r.fused
    streams = [f"{p.name}-{i}" for i in range(1, 7)]
    for stream in streams:
        r.grabber(stream)
    serving = poll(lambda: (s := services()["asr"]["serving"]) and set(streams) <= set(s) and s, timeout_s=60)
    assert len({serving[s] for s in streams}) == 3, serving  # every instance serves some of them
    first = poll(lambda: fused(streams[0]), timeout_s=120)
    victim = first[0]["anchor"]["instance"]
    assert victim == serving[streams[0]], (victim, serving)
    moved = [s for s in streams if serving[s] == victim]
    host = p.components()[victim]["host"]  # the container's hostname: its id
    run("docker", "kill", host)
    killed_ns = time.time_ns()
    after = poll(lambda: (s := services()["asr"]) and victim not in s["instances"] and s["serving"], timeout_s=15)
    assert all(after[s] != victim for s in moved), after

    truth = [normalise(t) for t in TRUTH * 2]
    results = {s: poll(lambda s=s: at_least(len(truth) - (3 if s in moved else 0), fused(s)), timeout_s=150)
               for s in streams}
    for stream, items in results.items():
        heard = [normalise(best_text(f)) for f in items]
        instances = {f["anchor"]["instance"] for f in items}
        if stream not in moved:  # all of its sentences, each decoded once, by the one instance serving it
            assert heard == truth, (stream, heard, p.logs())
            assert instances == {serving[stream]}, (stream, instances)
            continue
        # moved: decoded before the kill by the victim, after it by the survivor, nothing twice; the
        # survivor decodes whole sentences (the first it hears may be the tail of the utterance that
        # was in flight on the victim: "not understood", or the words it heard); an utterance the
        # victim had taken and not answered is fused without it, anchored on its VAD segment
        orphans = [f for f in items if f["anchor"]["type"] != "speech"]
        assert all(f["completion"] == "components_gone" and "asr" in f["missing_components"] for f in orphans), orphans
        instances = {f["anchor"]["instance"] for f in items if f not in orphans}
        assert instances <= {victim, after[stream]}, (stream, instances)
        later = [normalise(best_text(f)) for f in items if f["anchor"]["received_ns"] > killed_ns]
        assert any(text in truth for text in later), (stream, heard)
        assert all(heard.count(text) <= truth.count(text) for text in truth), (stream, heard)


def test_an_asr_replica_cut_off_the_network_is_dead_its_streams_move_and_reconnected_it_takes_work_again(
        project, tmp_path):
    """Network faults: `docker network disconnect` on the asr instance serving a stream:
    it is declared dead, its stream moves to the other replica, fusions stop waiting for it, and what
    was stored stays; connected again, it registers again under its id and takes the next stream."""
    r = Replicated(project, tmp_path, asr=2, copies=3)  # 63 s: a and b still play when c starts
    p, services, fused = r.p, r.services, r.fused
    a, b, c = (f"{p.name}-{x}" for x in "abc")
    for stream in (a, b):
        r.grabber(stream)
    poll(lambda: fused(a) and fused(b), timeout_s=120)
    serving = services()["asr"]["serving"]
    victim = serving[a]
    assert serving[b] != victim, serving  # balanced: one stream each
    network = f"{p.name}_esiaf"
    container = p.components()[victim]["host"]
    stored_before = {f["id"] for f in fused(a)}
    run("docker", "network", "disconnect", network, container)
    cut_ns = time.time_ns()
    try:
        poll(lambda: p.components()[victim]["status"] == "dead", timeout_s=10)
        assert services()["asr"]["serving"][a] == serving[b]  # moved to the survivor
        # the survivor decodes a's next sentences
        truth = {normalise(t) for t in TRUTH}
        poll(lambda: [f for f in fused(a) if f["anchor"]["received_ns"] > cut_ns
                      and normalise(best_text(f)) in truth and f["anchor"]["instance"] == serving[b]] or None,
             timeout_s=60)
    finally:
        run("docker", "network", "connect", network, container, check=False)
    poll(lambda: p.components().get(victim, {}).get("status") == "alive", timeout_s=30)  # registered again
    assert stored_before <= {f["id"] for f in fused(a)}  # nothing stored is lost
    r.grabber(c)  # a new stream: the least loaded instance takes it
    poll(lambda: services()["asr"]["serving"].get(c) == victim, timeout_s=30)
    taken = poll(lambda: fused(c), timeout_s=90)
    assert taken[0]["anchor"]["instance"] == victim and normalise(best_text(taken[0])) in truth, taken[0]

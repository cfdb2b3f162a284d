"""Replicas that share the work: two instances of one service, each stream served by
exactly one of them over real ZeroMQ subscriptions, and a killed instance's streams moving to the
survivor. The replicas are processes of their own (tests/replica_sink.py) so that one can be killed."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter

import numpy as np

from esiaf import AudioFormat, Component
from esiaf.tools.testing import REPO, poll

STREAMS = ["robot1", "robot2", "robot3", "robot4"]


class Source(Component):
    service = "source"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("source/audio", AudioFormat(16000, "int16"))
        self.script = []

    def produce(self):
        while not self.stopping:
            while self.script:
                self.script.pop(0)(self)
            self.sleep_until(time.monotonic() + 0.02)


def publish_round(source: Source, chunks: int) -> threading.Event:
    """``chunks`` chunks of each stream, published from the source's own thread."""
    done = threading.Event()

    def run(c: Source) -> None:
        for _ in range(chunks):
            for stream in STREAMS:
                now = time.time_ns()
                c.publish("source/audio", np.zeros(160, np.int16), now - 10_000_000, now, stream_id=stream)
        done.set()
    source.script.append(run)
    return done


def taken(path) -> Counter:
    return Counter(line.split()[0] for line in path.read_text().splitlines()) if path.exists() else Counter()


def test_replicas_share_the_streams_and_a_killed_ones_move_to_the_survivor(orchestrator, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    files = {name: tmp_path / f"{name}.txt" for name in ("sink-a", "sink-b")}
    replicas = {name: subprocess.Popen([sys.executable, str(REPO / "tests" / "replica_sink.py"), orchestrator.url,
                                        str(path), name], cwd=REPO, env=env, stderr=subprocess.DEVNULL)
                for name, path in files.items()}
    source = Source(Source.Settings(name="source", orchestrator_url=orchestrator.url))
    thread = threading.Thread(target=source.run, daemon=True)
    try:
        poll(lambda: len(orchestrator.http.get("/components").json()["services"].get("sink", {})
                         .get("instances", [])) == 2, timeout_s=30)
        thread.start()
        poll(lambda: source.control is not None and source.control.component_id, timeout_s=10)
        for stream in STREAMS:
            source.announce_stream(time.time_ns(), stream_id=stream)
        serving = poll(lambda: (s := orchestrator.http.get("/components").json()["services"]["sink"]["serving"])
                       and len(s) == 4 and s, timeout_s=10)
        assert Counter(serving.values()) == {"sink-a": 2, "sink-b": 2}  # balanced
        # each replica subscribed to its two streams at the source's XPUB: four subscriptions
        poll(lambda: source.output_stats["source/audio"].subscribers >= 4, timeout_s=10)

        assert publish_round(source, 20).wait(10)
        poll(lambda: sum(taken(f).total() for f in files.values()) >= 80, timeout_s=10)
        time.sleep(0.3)  # anything extra would have come by now
        for name, path in files.items():  # every message once, and only by the replica serving its stream
            assert taken(path) == {s: 20 for s, instance in serving.items() if instance == name}

        replicas["sink-b"].kill()  # dies without a word: declared dead, its streams move to sink-a
        replicas["sink-b"].wait()
        poll(lambda: set(orchestrator.http.get("/components").json()["services"]["sink"]["serving"].values())
             == {"sink-a"}, timeout_s=10)
        # sink-a, alone now, is told: it subscribes to the whole topic and drops its two streams (sink-b's two
        # went with its connection), one subscription at the source's XPUB
        poll(lambda: source.output_stats["source/audio"].subscribers == 1, timeout_s=10)
        assert publish_round(source, 10).wait(10)
        poll(lambda: taken(files["sink-a"]).total() >= 80, timeout_s=10)
        time.sleep(0.3)
        assert taken(files["sink-a"]) == {s: 30 if instance == "sink-a" else 10 for s, instance in serving.items()}
        # a publisher numbers each stream apart: a replica that hears half of them has lost nothing
        inputs = poll(lambda: (i := next(c["stats"]["inputs"]["source/audio"] for c in
                                         orchestrator.http.get("/components").json()["items"]
                                         if c["component_id"] == "sink-a")) and i["received"] == 80 and i,
                      timeout_s=10)
        assert inputs["lost"] == 0
    finally:
        source.stop()
        thread.join(timeout=10)
        for replica in replicas.values():
            if replica.poll() is None:
                replica.send_signal(signal.SIGTERM)
                replica.wait(timeout=10)

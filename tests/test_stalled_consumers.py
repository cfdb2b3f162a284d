"""Who a producer's audio waits for: a registered consumer that stops reading keeps its connection for
STALL_MS (a consumer frozen 20 s lost the audio behind the freeze at 4 s), and a subscriber without the
token, or one the orchestrator never named, gets no queue at all, so it neither holds a replay back nor
makes live audio drop. Real ZeroMQ sockets; the frozen consumer is a process stopped with SIGSTOP."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import zmq
from zmq.utils.monitor import recv_monitor_message

from esiaf.auth import TOKEN_ENV
from esiaf.proto import esiaf_pb2 as pb
from esiaf.receiving import Replays
from esiaf.tools.testing import REPO, poll
from esiaf.transport import UNACKED_MS, Transport

TOPIC = "source/audio"

# a consumer in a process of its own, that can be stopped: prints each sequence number it takes
CONSUMER = """
import sys
import zmq
from esiaf.proto import esiaf_pb2 as pb
from esiaf.transport import Transport

transport = Transport(zmq.Context(), inputs=[sys.argv[1]], has_outputs=False, bind_host="127.0.0.1", identity="sink")
transport.connect_peers({sys.argv[2]})
print("ready", flush=True)
while True:
    for kind, event in transport.events(1000):
        if kind == "audio":
            print(pb.AugmentedAudio.FromString(event[1]).sequence, flush=True)
"""


def message(sequence: int, stream_id: str = "s", size: int = 8000) -> pb.AugmentedAudio:
    audio = pb.AugmentedAudio(stream_id=stream_id, topic=TOPIC, publisher="source", sequence=sequence,
                              start_ns=sequence * 1_000_000, end_ns=(sequence + 1) * 1_000_000, payload=bytes(size))
    audio.format.sample_rate_hz, audio.format.channels = 16000, 1
    return audio


def subscribed(producer: Transport, until, timeout_s: float = 20) -> tuple[int, list[str]]:
    """Services the producer until ``until(subscriptions, refused)`` holds: the subscriptions (any topic) it
    has taken, and the reasons of the subscribers it refused."""
    seen, refused = 0, []
    deadline = time.monotonic() + timeout_s
    while not until(seen, refused):
        assert time.monotonic() < deadline, f"{seen} subscriptions, refused: {refused}"
        for kind, event in producer.events(200, take_audio=False):
            seen += kind == "subscription" and event[1] == 1
            refused += [event] if kind == "refused" else []
    return seen, refused


def test_a_consumer_frozen_longer_than_the_unacknowledged_data_timeout_keeps_its_live_audio():
    """Live audio (the default queue): the consumer is stopped, its kernel buffer fills, its TCP window
    closes; with the data timeout (4 s) the producer dropped the connection and all queued for it."""
    context = zmq.Context()
    producer = Transport(context, inputs=[], has_outputs=True, bind_host="127.0.0.1")
    producer.name_consumers("source-1", ["sink"])
    consumer = subprocess.Popen([sys.executable, "-c", CONSUMER, TOPIC, producer.audio_endpoint], cwd=REPO,
                                stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    taken: list[int] = []
    reader = threading.Thread(target=lambda: taken.extend(int(line) for line in consumer.stdout if line[0].isdigit()),
                              daemon=True)
    assert consumer.stdout is not None and consumer.stdout.readline().strip() == "ready"
    reader.start()
    monitor = producer.pub.get_monitor_socket(zmq.EVENT_DISCONNECTED)
    sent = 0
    try:
        subscribed(producer, lambda seen, _: seen == 1)
        for _ in range(20):
            sent += 1
            assert producer.send_audio(TOPIC, message(sent))[0]
        poll(lambda: len(taken) == sent, timeout_s=20)
        consumer.send_signal(signal.SIGSTOP)
        for _ in range(400):  # 3.2 MB: more than the stopped consumer's kernel takes, so its window closes
            sent += 1
            assert producer.send_audio(TOPIC, message(sent))[0]  # queued for it (live: never waits)
        # stopped longer than the data timeout: the connection stays (no disconnect within it and 3 s more)
        assert not monitor.poll(UNACKED_MS + 3000), recv_monitor_message(monitor)
        consumer.send_signal(signal.SIGCONT)
        poll(lambda: len(taken) >= sent, timeout_s=30)
        assert taken == list(range(1, sent + 1))  # nothing lost behind the freeze
    finally:
        consumer.send_signal(signal.SIGCONT)
        consumer.kill()
        consumer.wait()
        monitor.close(linger=0)
        producer.close()
        context.term()


@pytest.fixture
def token(monkeypatch):
    monkeypatch.setenv(TOKEN_ENV, "the-token")
    return "the-token"


def stranger(context: zmq.Context, endpoint: str, user: bytes | None = None, password: bytes | None = None):
    """A subscriber to everything that never reads, with a queue of one message."""
    sock = context.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVHWM, 1)
    sock.setsockopt(zmq.RCVBUF, 4096)
    if user is not None:
        sock.plain_username = user
    if password is not None:
        sock.plain_password = password
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.connect(endpoint)
    return sock


def test_a_replay_waits_only_for_the_consumers_the_orchestrator_named(token):
    """A subscriber without the token, and one with it under a name the orchestrator never named, both
    never reading: the replay (which waits for every consumer it queues for) runs at the named consumer's
    pace; before, each was given a queue and held it back until STALL_MS (60 s) dropped it."""
    context = zmq.Context()
    replays = Replays()
    replays.note("r", True)
    producer = Transport(context, inputs=[], has_outputs=True, bind_host="127.0.0.1", audio_queue=4, replays=replays)
    producer.name_consumers("source-1", ["sink-1"])
    strangers = [stranger(context, producer.audio_endpoint),  # no token: NULL against a PLAIN server
                 stranger(context, producer.audio_endpoint, b"stranger", token.encode())]  # not a named consumer
    sink_context = zmq.Context()
    sink = Transport(sink_context, inputs=[TOPIC], has_outputs=False, bind_host="127.0.0.1", audio_queue=4,
                     identity="sink-1")
    sink.connect_peers({producer.audio_endpoint})
    taken: list[int] = []
    reading = threading.Event()
    reading.set()

    def read() -> None:
        while reading.is_set():
            for kind, event in sink.events(100):
                if kind == "audio":
                    taken.append(pb.AugmentedAudio.FromString(event[1]).sequence)

    reader = threading.Thread(target=read, daemon=True)
    try:
        # the named consumer subscribed, both strangers refused at the handshake and counted (the one with
        # the token once it has been held HOLD_S); without the gate the one without it subscribed too
        seen, _ = subscribed(producer, lambda seen, refused: seen > 1 or (
            seen == 1 and {"protocol", "auth"} <= set(refused)))
        reader.start()
        chunks, done = 300, threading.Event()

        def play() -> None:
            for n in range(1, chunks + 1):
                assert producer.send_audio(TOPIC, message(n, "r", size=3200))[0]
            done.set()

        threading.Thread(target=play, daemon=True).start()
        assert done.wait(timeout=15), f"the replay is held back: {len(taken)} of {chunks} taken"
        poll(lambda: len(taken) == chunks, timeout_s=15)
        assert taken == list(range(1, chunks + 1))
        assert seen == 1, "a stranger was taken as a subscriber"
    finally:
        reading.clear()
        if reader.is_alive():
            reader.join(timeout=5)
        for sock in strangers:
            sock.close(linger=0)
        sink.close()
        producer.close()
        sink_context.term()
        context.term()

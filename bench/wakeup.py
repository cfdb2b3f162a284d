"""What one message costs a bare pyzmq PUB -> SUB pair, back to back and paced: the floor under the SDK.

    python -m bench.wakeup [--messages 300] [--periods-ms 0,20,50,100] [--no-work]

A publisher sends 700-byte two-frame messages (a 20 ms chunk's size) over TCP on loopback to a
subscriber in another process, one every period (0: back to back), and reports per message the
CPU of the publishing thread's send, of the publisher's process (with libzmq's I/O thread) and of
the subscriber's process. Paced, most of it is waking threads (each process's libzmq I/O thread
and the receiving thread), not Python: no code on the per-message path can go below it; fewer
messages can (docs/benchmarks.md, "The framework's CPU per hour of audio").

Then the same for work, not messages: the thread CPU of one Silero VAD window (the vad's
``Session.run`` on 32 ms of audio) and of a small numpy step (a 128 x 512 product and a tanh), run
back to back and once per period in a thread that sleeps in between. On this machine code that ran
a period ago runs several times slower than code run a moment ago (its caches are cold): the
reason the vad's handler costs the vad process about four times what it costs back to back.
"""
from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time

import zmq

SUBSCRIBER = """
import resource, sys, zmq
def cpu_s():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime
socket = zmq.Context().socket(zmq.SUB)
socket.setsockopt(zmq.SUBSCRIBE, b"")
socket.connect(sys.argv[1])
socket.recv_multipart()  # the first message: from here on it counts
started = cpu_s()
while socket.recv_multipart()[-1] != b"end":
    pass
print(cpu_s() - started)
"""


def cpu_s() -> float:
    """This process's CPU so far, every thread (libzmq's too), to the microsecond."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def measure(period_s: float, messages: int) -> tuple[float, float, float]:
    """µs per message: the send call's thread CPU, the publisher's process, the subscriber's."""
    context = zmq.Context()
    pub = context.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    subscriber = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, f"tcp://127.0.0.1:{port}"],
                                  stdout=subprocess.PIPE, text=True)
    try:
        time.sleep(1.0)  # the subscription arrives
        payload, sending = b"x" * 700, 0.0
        pub.send_multipart([b"grabber/audio\0", payload])  # the subscriber's start
        mine = cpu_s()
        for _ in range(messages):
            if period_s:
                time.sleep(period_s)
            started = time.thread_time()
            pub.send_multipart([b"grabber/audio\0", payload], flags=zmq.NOBLOCK)
            sending += time.thread_time() - started
        mine = cpu_s() - mine
        pub.send_multipart([b"t", b"end"])
        theirs = float(subscriber.communicate(timeout=10)[0])
    finally:
        subscriber.kill()
        pub.close()
        context.term()
    return sending / messages * 1e6, mine / messages * 1e6, theirs / messages * 1e6


def cold_work(period_s: float, repeats: int) -> tuple[float, float]:
    """µs of thread CPU per call: one Silero window, one numpy step; one call per period (0: back to back)."""
    import numpy as np

    from esiaf.speech.silero import SileroModel
    stream = SileroModel().stream(16000)
    window = (np.random.default_rng(0).standard_normal(512) * 0.1).astype(np.float32)
    weights = np.random.default_rng(1).standard_normal((128, 512)).astype(np.float32)
    silero = numpy = 0.0
    for _ in range(repeats):
        if period_s:
            time.sleep(period_s)
        started = time.thread_time()
        stream.probabilities(window)
        silero += time.thread_time() - started
        if period_s:
            time.sleep(period_s)
        started = time.thread_time()
        float(np.tanh(weights @ window).sum())
        numpy += time.thread_time() - started
    return silero / repeats * 1e6, numpy / repeats * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--messages", type=int, default=300)
    parser.add_argument("--periods-ms", default="0,20,50,100", help="pacing, ms (0: back to back)")
    parser.add_argument("--no-work", action="store_true", help="messages only: not the Silero window and numpy step")
    args = parser.parse_args()
    print("| period | send call | publisher process | subscriber process |\n|---|---|---|---|")
    for period_ms in (float(p) for p in args.periods_ms.split(",")):
        send, publisher, subscriber = measure(period_ms / 1000, args.messages)
        print(f"| {period_ms:g} ms | {send:.0f} µs | {publisher:.0f} µs | {subscriber:.0f} µs |")
    if not args.no_work:
        print("\n| period | one Silero window (Session.run) | a numpy step (128 x 512 product, tanh) |\n|---|---|---|")
        for period_ms in (float(p) for p in args.periods_ms.split(",")):
            silero, numpy = cold_work(period_ms / 1000, args.messages)
            print(f"| {period_ms:g} ms | {silero:.0f} µs | {numpy:.0f} µs |")
    with open("/proc/loadavg") as handle:
        print("load average:", " ".join(handle.read().split()[:3]))


if __name__ == "__main__":
    main()

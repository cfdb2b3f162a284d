"""The ros2 service's latency: a fused result on /humans/voices/<id>/speech after the websocket, and
an utterance's beamformed audio on /humans/voices/<id>/audio.

    python bench/ros2.py [--count 300] [--rate 20] [--domain 150]
    python bench/ros2.py --scene examples/robocup_scene.flac [--port 21500] [--domain 150]

A websocket server here sends fused results (docs/protocol.md's shape, a LiveSpeech's worth each) to two
clients at once: the ros2 service (python -m esiaf_services.ros2, a process of its own) and this
script's own websocket client; this script also reads /humans/voices/voice_1/speech over DDS. The
latency of each result is the time its LiveSpeech arrives here minus the time the same result arrived
on this script's websocket (side by side, one clock). Prints ``name=value`` lines; the target is a p95
of at most 20 ms.

With ``--scene`` (a 4-channel recording of the respeaker4 array), the whole pipeline runs instead
(``esiaf run --array respeaker4 --grammar robocup --ros2``, played in real time): for each recognised
utterance, the time its AudioData arrives here after the same fused result arrived on this script's
websocket, and after the utterance's end (its capture time, which a real-time playback stamps from
the wall clock).
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from cyclonedds.util import duration  # noqa: E402
from websockets.exceptions import ConnectionClosed  # noqa: E402
from websockets.sync.client import connect  # noqa: E402
from websockets.sync.server import ServerConnection, serve  # noqa: E402

from esiaf import auth  # noqa: E402
from esiaf.tools.feed import FusedFeed  # noqa: E402
from esiaf.tools.testing import free_port, poll  # noqa: E402
from esiaf_services.ros2.dds import ROS2_DEFAULT_QOS  # noqa: E402
from esiaf_services.ros2.messages import AudioData, LiveSpeech  # noqa: E402

VOICES = [f"voice_{n}" for n in range(1, 6)] + [f"track_{n}" for n in range(1, 10)] + ["unknown"]


def fused(n: int) -> str:
    start_ns = 1_700_000_000_000_000_000 + n * 2_000_000_000
    return json.dumps({
        "type": "fused_result", "id": n, "revision": 1, "fusion": "speech", "stream_id": "bench", "seq": n,
        "anchor": {"type": "speech", "span": {"start_ns": start_ns, "end_ns": start_ns + 1_500_000_000},
                   "speech": {"hypotheses": [{"text": f"question {n}", "probability": 0.9, "words": []}]}},
        "results": {"voice_id": [{"voice_id": {"label": "voice-1", "probability": 1.0, "class_probabilities": {}}}]},
        "aggregates": {"voice_id": {"label": "voice-1", "probability": 1.0},
                       "emotion": {"label": "neutral", "probability": 0.7, "distribution": {}, "overlap_s": 1.5},
                       "gender": {"label": "female", "probability": 0.9, "distribution": {}, "overlap_s": 1.5}},
        "completion": "complete", "missing_components": [], "missing": [], "published_ns": start_ns})


def percentiles(name: str, values_ms: list[float]) -> None:
    values = np.array(values_ms)
    for label, q in (("p50", 50), ("p95", 95)):
        print(f"{name}_{label}_ms={np.percentile(values, q):.1f}")
    print(f"{name}_max_ms={values.max():.1f}")


def scene(args: argparse.Namespace) -> None:
    """The audio topic's delivery through the whole pipeline (see the module's docstring)."""
    os.environ[auth.TOKEN_ENV] = auth.token() or auth.new_token()
    participant = DomainParticipant(args.domain)
    readers = {voice: DataReader(participant, Topic(participant, f"rt/humans/voices/{voice}/audio", AudioData,
                                                    qos=ROS2_DEFAULT_QOS), qos=ROS2_DEFAULT_QOS)
               for voice in VOICES}
    audio_at: dict[str, list[tuple[float, int, int]]] = {}  # voice -> (monotonic, wall ns, bytes), as they come
    ws_at: dict[str, list[tuple[float, int]]] = {}  # voice -> (monotonic, span end ns) of each first revision
    done = threading.Event()

    def read_dds() -> None:
        while not done.is_set():
            for voice, reader in readers.items():
                for sample in reader.take(N=10):
                    if isinstance(sample, AudioData):
                        audio_at.setdefault(voice, []).append((time.monotonic(), time.time_ns(), len(sample.data)))
            time.sleep(0.002)

    threading.Thread(target=read_dds, daemon=True).start()
    with tempfile.TemporaryDirectory() as tmp:
        run = subprocess.Popen([sys.executable, "-m", "esiaf", "run", "--input", str(args.scene), "--array",
                                "respeaker4", "--grammar", "robocup", "--ros2", "--port", str(args.port),
                                "--workdir", tmp], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env={**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": str(args.domain)})
        try:
            feed = poll(lambda: _feed(f"ws://127.0.0.1:{args.port}/ws/fused"), 120)
            with feed:
                while run.poll() is None:
                    try:
                        message = json.loads(feed.recv(timeout=0.5))
                    except TimeoutError:
                        continue
                    if message.get("type") == "fused_result" and message.get("revision") == 1 and \
                            message["anchor"].get("speech"):
                        label = (message["aggregates"].get("voice_id") or {}).get("label") or "unknown"
                        ws_at.setdefault(label.replace("-", "_"), []).append(
                            (time.monotonic(), int(message["anchor"]["span"]["end_ns"])))
            time.sleep(1.0)
        finally:
            done.set()
            run.terminate()
            run.wait(timeout=30)
    after_ws, after_end = [], []
    for voice, fused in ws_at.items():
        for (ws_s, end_ns), (dds_s, wall_ns, _) in zip(fused, audio_at.get(voice, []), strict=False):
            after_ws.append((dds_s - ws_s) * 1000)
            after_end.append((wall_ns - end_ns) / 1e6)
    print(f"utterances={sum(len(f) for f in ws_at.values())}")
    print(f"audio_received={sum(len(a) for a in audio_at.values())}")
    print(f"audio_bytes={sum(b for a in audio_at.values() for _, _, b in a)}")
    percentiles("ros2_audio_after_websocket", after_ws)
    percentiles("ros2_audio_after_utterance_end", after_end)


def _feed(url: str) -> FusedFeed | None:
    try:
        return FusedFeed(url)
    except (OSError, TimeoutError, ConnectionClosed):
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=300, help="fused results sent (default 300)")
    parser.add_argument("--rate", type=float, default=20.0, help="fused results per second (default 20)")
    parser.add_argument("--domain", type=int, default=150, help="the DDS domain (default 150)")
    parser.add_argument("--scene", type=Path, help="a 4-channel respeaker4 recording: the audio topic's delivery")
    parser.add_argument("--port", type=int, default=21500, help="--scene: the orchestrator's port (default 21500)")
    args = parser.parse_args()
    if args.scene:
        scene(args)
        return
    clients: list[ServerConnection] = []
    go = threading.Event()

    def handler(connection: ServerConnection) -> None:
        clients.append(connection)
        go.wait()
        with contextlib.suppress(ConnectionClosed):
            connection.recv()  # until it goes

    ws_at: dict[str, float] = {}
    dds_at: dict[str, float] = {}
    participant = DomainParticipant(args.domain)
    reader = DataReader(participant, Topic(participant, "rt/humans/voices/voice_1/speech", LiveSpeech,
                                           qos=ROS2_DEFAULT_QOS), qos=ROS2_DEFAULT_QOS)

    def read_dds() -> None:
        for sample in reader.take_iter(timeout=duration(seconds=10)):
            if isinstance(sample, LiveSpeech):
                dds_at[sample.final] = time.monotonic()

    port = free_port()
    with serve(handler, "127.0.0.1", port) as server, tempfile.TemporaryDirectory() as tmp:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        log = Path(tmp) / "ros2.log"
        with log.open("w") as out:
            bridge = subprocess.Popen([sys.executable, "-m", "esiaf_services.ros2"], cwd=REPO, stdout=out,
                                      stderr=subprocess.STDOUT,
                                      env={**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": str(args.domain),
                                           "ESIAF_ORCHESTRATOR_URL": f"http://127.0.0.1:{port}"})
        try:
            poll(lambda: len(clients) == 1, 30)
            with connect(f"ws://127.0.0.1:{port}") as mine:
                poll(lambda: len(clients) == 2, 10)
                go.set()
                threading.Thread(target=read_dds, daemon=True).start()
                warm = fused(0)
                for client in clients:  # the bridge's writer made and matched before the timing
                    client.send(warm)
                mine.recv(timeout=5)
                poll(lambda: "question 0" in dds_at, 10)

                def read_ws() -> None:
                    for _ in range(args.count):
                        text = mine.recv(timeout=10)
                        ws_at[json.loads(text)["anchor"]["speech"]["hypotheses"][0]["text"]] = time.monotonic()

                ws_reader = threading.Thread(target=read_ws)
                ws_reader.start()
                for n in range(1, args.count + 1):
                    text = fused(n)
                    for client in (clients if n % 2 else clients[::-1]):  # neither always first
                        client.send(text)
                    time.sleep(1 / args.rate)
                ws_reader.join()
                poll(lambda: len(dds_at) >= args.count + 1, 10)
        finally:
            bridge.terminate()
            bridge.wait(timeout=10)
    latencies = np.array([(dds_at[k] - ws_at[k]) * 1000 for k in ws_at if k in dds_at])
    print(f"results={args.count}")
    print(f"received={len(latencies)}")
    for name, q in (("p50", 50), ("p95", 95), ("p99", 99)):
        print(f"ros2_speech_latency_{name}_ms={np.percentile(latencies, q):.2f}")
    print(f"ros2_speech_latency_max_ms={latencies.max():.2f}")


if __name__ == "__main__":
    main()

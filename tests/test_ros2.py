"""The ros2 service seen from ROS 2's side: a DDS subscriber in another process (tests/ros2_listener.py,
its types declared from the hri_msgs and audio_common_msgs .msg files) hears the demo's questions as
LiveSpeech on the voice ids the fused results name, the tracked voices about once a second, and each
utterance's beamformed audio on its voice; a websocket message the bridge cannot map is counted and
logged, and the next one is still published."""
from __future__ import annotations

import base64
import contextlib
import json
import os
import random
import statistics
import subprocess
import sys
import threading
from itertools import pairwise

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.server import serve

from esiaf.tools.testing import REPO, free_port, normalise, poll

pytest.importorskip("cyclonedds", reason="the ros2 extra (pip install 'esiaf[ros2]')")

pytestmark = pytest.mark.e2e
LISTENER = REPO / "tests" / "ros2_listener.py"
CANDIDATE_IDS = [f"voice_{n}" for n in range(1, 6)] + ["unknown"]


class Listener:
    """tests/ros2_listener.py as a child process; its samples collected as they come."""

    def __init__(self, domain: int, seconds: float, ids: list[str]) -> None:
        self.samples: list[dict] = []
        self.process = subprocess.Popen([sys.executable, str(LISTENER), "--seconds", str(seconds), *ids],
                                        stdout=subprocess.PIPE, text=True,
                                        env={**os.environ, "ROS_DOMAIN_ID": str(domain)})
        threading.Thread(target=self._read, daemon=True).start()
        poll(lambda: any(s.get("ready") for s in self.samples), 30)

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.samples.append(json.loads(line))

    def on(self, suffix: str) -> list[dict]:
        return [s for s in self.samples if s.get("topic", "").endswith(suffix)]

    def stop(self) -> None:
        self.process.kill()
        self.process.wait()


@pytest.fixture
def domain() -> int:
    """A DDS domain of this test's own, so that other runs on this machine are not heard."""
    return random.randint(100, 200)


@pytest.fixture
def listener(domain):
    listeners: list[Listener] = []

    def start(seconds: float, ids: list[str]) -> Listener:
        listeners.append(Listener(domain, seconds, ids))
        return listeners[-1]

    yield start
    for started in listeners:
        started.stop()


def expected_voice(fused: dict) -> str:
    """The voice id a fused result's speech goes to (docs/ros2.md): its voice_id label, '-' made '_';
    else 'unknown' (no microphone array here, so no ssl track)."""
    label = (fused["aggregates"].get("voice_id") or {}).get("label")
    return label.replace("-", "_") if label and label != "unknown" else "unknown"


def test_the_demo_questions_arrive_as_livespeech_on_their_voices(launch, listener, domain):
    truth = json.loads((REPO / "examples" / "robocup_questions.json").read_text())["sentences"]
    heard = listener(180, CANDIDATE_IDS)
    run = launch("--input", str(REPO / "examples" / "robocup_questions.wav"), "--grammar", "robocup", "--ros2",
                 "--json", env={"ROS_DOMAIN_ID": str(domain)})
    assert run.process.wait(timeout=150) == 0, run.describe()
    fused = [line for line in run.lines if line.get("type") == "fused_result" and line["anchor"].get("speech")]
    assert len(fused) == len(truth) == 5
    wanted = sorted((expected_voice(f), f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused)
    assert all(voice in CANDIDATE_IDS for voice, _ in wanted), wanted

    def said() -> list[tuple[str, str]]:
        return sorted((s["topic"].split("/")[3], s["data"]["final"]) for s in heard.on("/speech")
                      if s["data"]["final"])

    assert poll(lambda: said() == wanted, 10), f"LiveSpeech {said()} != fused {wanted}"
    assert [normalise(text) for _, text in said()] == sorted(normalise(s["text"]) for s in truth)
    for sample in heard.on("/speech"):
        assert bool(sample["data"]["incremental"]) != bool(sample["data"]["final"])  # one or the other
        assert 0.0 <= sample["data"]["confidence"] <= 1.0 and sample["data"]["language"] == "en-US"
    # the partial results, while each question went on (the stream's first is decoded whole): on the
    # voice "unknown", as nobody is known before the utterance is fused
    incremental = [s for s in heard.on("/speech") if s["data"]["incremental"]]
    assert {s["topic"].split("/")[3] for s in incremental} == {"unknown"} and len(incremental) >= 8
    speaking = [(s["topic"].split("/")[3], s["data"]["data"]) for s in heard.on("/is_speaking")]
    named = [value for voice, value in speaking if voice != "unknown"]
    assert named.count(True) == named.count(False) == 5
    unknown = [value for voice, value in speaking if voice == "unknown"]
    assert unknown.count(True) == unknown.count(False) >= 3  # each partial utterance, opened and closed
    # the tracked voices, republished at 1 Hz through the 21 s played in real time
    tracked = heard.on("/humans/voices/tracked")
    assert len(tracked) >= 15, len(tracked)
    gaps = [b["received_s"] - a["received_s"] for a, b in pairwise(tracked)]
    assert 0.8 <= statistics.median(gaps) <= 1.2, gaps
    assert {voice for voice, _ in wanted} <= {i for s in tracked for i in s["data"]["ids"]}


def test_each_utterance_s_beamformed_audio_arrives_on_its_voice(launch, listener, domain):
    """The 4-channel demo through the array (ssl, beamformer): each fused utterance's audio is on
    /humans/voices/<id>/audio as AudioData, as long as its span, and speech (not silence)."""
    tracks = [f"track_{n}" for n in range(1, 10)]
    heard = listener(180, CANDIDATE_IDS + tracks)
    run = launch("--input", str(REPO / "examples" / "robocup_scene.flac"), "--array", "respeaker4",
                 "--grammar", "robocup", "--ros2", "--fast", "--json", env={"ROS_DOMAIN_ID": str(domain)})
    assert run.process.wait(timeout=150) == 0, run.describe()
    fused = [line for line in run.lines if line.get("type") == "fused_result" and line["anchor"].get("speech")
             and line.get("revision", 1) == 1]
    assert len(fused) == 5, run.describe()

    def voice_of(result: dict) -> str:  # docs/ros2.md: the voice_id label, else the ssl track, else unknown
        label = (result["aggregates"].get("voice_id") or {}).get("label")
        track = (result["aggregates"].get("ssl") or {}).get("source_id")
        return label.replace("-", "_") if label and label != "unknown" else f"track_{track}" if track else "unknown"

    wanted = sorted((voice_of(f), f["anchor"]["span"]["end_ns"] - f["anchor"]["span"]["start_ns"]) for f in fused)
    assert all(voice in CANDIDATE_IDS + tracks for voice, _ in wanted), wanted
    assert poll(lambda: len(heard.on("/audio")) >= len(wanted), 10), f"{len(heard.on('/audio'))} audio samples"
    got = sorted(((s["topic"].split("/")[3], np.frombuffer(base64.b64decode(s["data"]["data"]), dtype="<i2"))
                  for s in heard.on("/audio")), key=lambda voice_samples: (voice_samples[0], len(voice_samples[1])))
    assert [voice for voice, _ in got] == [voice for voice, _ in wanted]
    for (voice, span_ns), (_, samples) in zip(wanted, got, strict=True):
        assert abs(len(samples) - span_ns * 16000 / 1e9) <= 0.05 * 16000, (voice, len(samples), span_ns)
        rms = float(np.sqrt(np.mean(samples.astype(float) ** 2)))
        assert rms > 300, (voice, rms)  # speech at -3 dBFS peak; silence or a constant is not


GOOD = {"type": "fused_result", "id": 1, "revision": 1, "fusion": "speech", "stream_id": "robot-1",
        "anchor": {"type": "speech",
                   "span": {"start_ns": 1_700_000_000_000_000_000, "end_ns": 1_700_000_001_000_000_000},
                   "speech": {"hypotheses": [{"text": "go to the kitchen", "probability": 0.8, "words": []}]}},
        "results": {"voice_id": [{"voice_id": {"label": "voice-3", "probability": 1.0,
                                               "class_probabilities": {"Anna": 0.41, "Bob": 0.12}}}]},
        "aggregates": {"voice_id": {"label": "voice-3", "probability": 1.0}}, "completion": "complete",
        "missing_components": [], "missing": [], "published_ns": 1_700_000_001_500_000_000, "seq": 1}
BAD = ["not json at all", "[1, 2]", json.dumps({"type": "fused_result", "stream_id": "robot-1"}),
       json.dumps({**GOOD, "anchor": {"span": {"start_ns": "soon"}}}), json.dumps({"type": "surprise"})]


@contextlib.contextmanager
def orchestrator_feed(messages: list[str]):
    """A websocket server written here from docs/protocol.md's fused results: it sends ``messages`` to
    each client, then waits for it to go. Yields its port."""

    def handler(connection) -> None:
        for text in messages:
            connection.send(text)
        with contextlib.suppress(ConnectionClosed):
            connection.recv()  # until the bridge goes

    port = free_port()
    with serve(handler, "127.0.0.1", port) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        yield port


@contextlib.contextmanager
def bridge(port: int, domain: int, log_path, env: dict[str, str] | None = None):
    """python -m esiaf_services.ros2 following ws://127.0.0.1:port; stopped with SIGTERM, it must exit 0."""
    with log_path.open("w") as log_file:
        process = subprocess.Popen([sys.executable, "-m", "esiaf_services.ros2"], cwd=REPO, stdout=log_file,
                                   stderr=subprocess.STDOUT,
                                   env={**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": str(domain),
                                        "ESIAF_ORCHESTRATOR_URL": f"http://127.0.0.1:{port}", **(env or {})})
    try:
        yield process
    finally:
        process.terminate()
        assert process.wait(timeout=10) == 0, log_path.read_text()


def test_messages_it_cannot_map_are_counted_and_the_next_is_published(listener, domain, tmp_path):
    """The bad messages, then a good one: the bridge logs each refusal, stays up and publishes the good one."""
    heard = listener(60, ["voice_3"])
    log_path = tmp_path / "ros2.log"
    with orchestrator_feed([*BAD, json.dumps(GOOD)]) as port, bridge(port, domain, log_path) as process:
        speech = poll(lambda: heard.on("/humans/voices/voice_3/speech"), 30)
        assert speech[0]["data"]["final"] == "go to the kitchen"
        match = poll(lambda: heard.on("/humans/candidate_matches"), 10)[0]["data"]
        assert (match["id1"], match["id1_type"], match["id2"], match["id2_type"]) == ("voice_3", 4, "Anna", 1)
        assert match["confidence"] == pytest.approx(0.41)
        assert process.poll() is None, log_path.read_text()
        log = log_path.read_text()
        for reason in ("not_json", "not_an_object", "bad_fused_result", "unknown_type"):
            assert f"reason={reason}" in log, log
        assert "Traceback" not in log
    counted = "refused={'not_json': 1, 'not_an_object': 1, 'bad_fused_result': 2, 'unknown_type': 1}"
    assert counted in log_path.read_text()


def test_three_robots_streams_keep_their_voices_apart(listener, domain, tmp_path):
    """One bridge, three streams, a namespace each: each robot's voice-1 says its own sentence, under
    its own /<stream>/humans/..., and each namespace's tracked list has only its own voice."""
    robots = {f"robot-{n}": f"sentence of robot {n}" for n in (1, 2, 3)}
    messages = [json.dumps({**GOOD, "id": n, "stream_id": stream, "aggregates": {"voice_id": {"label": "voice-1"}},
                            "anchor": {**GOOD["anchor"], "speech": {"hypotheses": [
                                {"text": text, "probability": 0.5, "words": []}]}}})
                for n, (stream, text) in enumerate(robots.items(), start=1)]
    heard = listener(60, ["voice_1", "--namespace=/robot_1", "--namespace=/robot_2", "--namespace=/robot_3"])
    with orchestrator_feed(messages) as port, bridge(port, domain, tmp_path / "ros2.log",
                                                     {"ESIAF_ROS2_NAMESPACE_PER_STREAM": "true"}):
        poll(lambda: len(heard.on("/voice_1/speech")) == 3, 30)
        said = {s["topic"]: s["data"]["final"] for s in heard.on("/voice_1/speech")}
        assert said == {f"/{stream.replace('-', '_')}/humans/voices/voice_1/speech": text
                        for stream, text in robots.items()}
        poll(lambda: {s["topic"] for s in heard.on("/tracked")} ==
             {f"/robot_{n}/humans/voices/tracked" for n in (1, 2, 3)}, 10)
        assert all(s["data"]["ids"] == ["voice_1"] for s in heard.on("/tracked"))


def test_a_bad_ros_domain_id_is_one_line(tmp_path):
    done = subprocess.run([sys.executable, "-m", "esiaf_services.ros2"], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": "robot"}, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == ["ros2: ROS_DOMAIN_ID='robot': not a DDS domain id (an integer 0..232)"]

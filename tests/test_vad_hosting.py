"""The vad as a guest in the grabber's process (esiaf/hosting.py): the same segments and speech as the
vad in a process of its own, both services registered under their own names, a guest's exception
counted without stopping the grabber (real orchestrator, real ZeroMQ sockets, the real Silero VAD)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import pytest
import soundfile

from esiaf import Audio, AudioFormat, Component
from esiaf.tools.testing import REPO, Orchestrator, normalise, poll
from esiaf_services.grabber.service import Grabber, GrabberSettings
from tests.test_bad_input import assert_clear, esiaf_run

pytestmark = pytest.mark.e2e
SCENE = REPO / "examples" / "robocup_scene.flac"
TRUTH = json.loads(SCENE.with_suffix(".json").read_text())["utterances"][:2]
SPEECH = AudioFormat(16000, "int16")


class Recorder(Component):
    """Records what it hears on ``heard`` (what the vad forwards on vad/speech) until the stream ends."""

    service = "recorder"
    heard = "vad/speech"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_input(self.heard, SPEECH)
        self.chunks: list[Audio] = []

    def on_audio(self, audio: Audio):
        self.chunks.append(audio)


class Faulty(Recorder):
    """A guest of the grabber whose handler fails on every chunk."""

    service = "faulty"
    heard = "grabber/audio"

    def on_audio(self, audio: Audio):
        raise RuntimeError("a guest's bug")


@pytest.fixture(scope="module")
def speech_48k(tmp_path_factory) -> Path:
    """The demo scene's first two questions, microphone 0, as 48 kHz mono: the vad (16 kHz) hears it converted."""
    import soxr
    mics, rate = soundfile.read(str(SCENE), dtype="float32", frames=int((TRUTH[-1]["end_s"] + 1.0) * 16000))
    path = tmp_path_factory.mktemp("speech") / "speech48k.wav"
    soundfile.write(str(path), soxr.resample(mics[:, 0], rate, 48000), 48000, subtype="PCM_16")
    return path


def start(component: Component) -> threading.Thread:
    thread = threading.Thread(target=component.run, daemon=True)
    thread.start()
    return thread


def service(name: str, args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", f"esiaf_services.{name}", *args], cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO), **env},
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)


def play(tmp_path: Path, path: Path, hosted: bool) -> tuple[list[tuple], list[tuple], dict[str, dict]]:
    """Plays ``path`` (50 ms chunks, in real time: the registrations are read while it plays) through
    grabber and vad, hosted or apart; returns the speech forwarded and the VAD results (spans from the
    stream's start) and the registrations."""
    workdir = tmp_path / ("hosted" if hosted else "apart")
    workdir.mkdir()
    orchestrator = Orchestrator(workdir)
    env = {"ESIAF_ORCHESTRATOR_URL": orchestrator.url, "ESIAF_STREAM_ID": "s"}
    recorder = Recorder(Recorder.Settings(name="recorder", orchestrator_url=orchestrator.url, stream_id="s"))
    children = []
    try:
        thread = start(recorder)
        grabber_env = {**env, "ESIAF_GRABBER_CHUNK_MS": "50", "ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"}
        if hosted:
            grabber_env.update(ESIAF_GRABBER_GUESTS='["vad"]', ESIAF_GRABBER_WAIT_TOPIC="vad/speech")
        else:
            children.append(service("vad", [], env, workdir / "vad.log"))
            poll(lambda: orchestrator.component("vad"), timeout_s=60)
        grabber = service("grabber", ["--input", str(path)], grabber_env, workdir / "grabber.log")
        children.append(grabber)
        # registrations while both live: the grabber waits for the recorder's subscription before it plays
        components = poll(lambda: (found := {c["name"]: c for c in orchestrator.http.get("/components").json()["items"]
                                             if c["status"] == "alive"}).keys() >= {"grabber", "vad"} and found,
                          timeout_s=60)
        poll(lambda: recorder.chunks and recorder.chunks[-1].end_of_stream, timeout_s=60)
        assert grabber.wait(timeout=30) == 0, (workdir / "grabber.log").read_text()
        origin = orchestrator.http.get("/streams/s").json()["start_ns"]
        speech = [(c.start_ns - origin, c.end_ns - origin, c.payload, c.meta.segmentation_ended,
                   c.meta.segment.start_ns - origin if c.meta.segment.end_ns else None, c.end_of_stream)
                  for c in recorder.chunks]
        results = poll(lambda: orchestrator.http.get("/results", params={"type": "vad"}).json()["items"],
                       timeout_s=10)
        vad = [(r["span"]["start_ns"] - origin, r["span"]["end_ns"] - origin, r["component"],
                r["vad"]["probability"]) for r in results]
        recorder.stop()
        thread.join(timeout=10)
        return speech, vad, components
    finally:
        for child in children:
            if child.poll() is None:
                child.terminate()
                child.wait(timeout=10)
        orchestrator.close()


@pytest.mark.parametrize("windows", [False, True], ids=["per_chunk", "per_window"])
def test_the_hosted_vad_cuts_and_forwards_what_the_vad_in_its_own_process_does(tmp_path, monkeypatch, speech_48k,
                                                                               windows):
    monkeypatch.setenv("ESIAF_VAD_SILERO__WINDOWS", str(windows).lower())
    apart, apart_vad, alone = play(tmp_path, speech_48k, hosted=False)
    hosted, hosted_vad, together = play(tmp_path, speech_48k, hosted=True)

    assert len(apart_vad) >= 2 and sum(chunk[3] for chunk in apart) == len(apart_vad), apart_vad
    assert hosted_vad == apart_vad  # the same segments, from the service named vad, with the same probabilities
    assert hosted == apart  # the same speech, to the last byte, with the same spans and marks

    assert alone["vad"]["pid"] != alone["grabber"]["pid"]
    # hosted: one process, two services, each under its own name and id, with its own heartbeat and info
    vad, grabber = together["vad"], together["grabber"]
    assert vad["pid"] == grabber["pid"] and vad["component_id"] != grabber["component_id"]
    assert vad["component_id"].startswith("vad") and vad["kind"] == "vad"
    assert grabber["info"]["guests"] == ["vad"]
    assert vad["audio_endpoint"] == grabber["audio_endpoint"]  # vad/speech leaves by the grabber's socket
    assert vad["info"]["backend"] == "silero"  # its own info, as it registered


def test_a_guest_that_fails_on_every_chunk_is_counted_and_the_grabber_plays_on(orchestrator, monkeypatch,
                                                                                 speech_48k):
    monkeypatch.setenv("ESIAF_ORCHESTRATOR_URL", orchestrator.url)
    grabber = Grabber(GrabberSettings(name="grabber", orchestrator_url=orchestrator.url, input=str(speech_48k),
                                      fast=True, chunk_ms=50, guests=[f"{__name__}:Faulty"]))
    thread = start(grabber)
    thread.join(timeout=60)
    node = grabber.context.node
    assert not thread.is_alive() and node is not None and node.exit_code == 0
    faulty = node.processors[1]
    played = grabber.output_stats["grabber/audio"].published
    assert played == -(-soundfile.info(str(speech_48k)).frames // 2400)  # every 50 ms chunk, to the end
    assert faulty.input_stats["grabber/audio"].received == played
    assert faulty.input_stats["grabber/audio"].bad == played


def test_a_guest_that_hears_nothing_of_its_host_stops_it_at_start_up(speech_48k):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9",
           "ESIAF_GRABBER_GUESTS": json.dumps(["vad"]), "ESIAF_VAD_INPUT_TOPIC": "splitter/ch0"}
    result = subprocess.run([sys.executable, "-m", "esiaf_services.grabber", "--input", str(speech_48k)], cwd=REPO,
                            env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines()[-1] == \
        "grabber: guest vad hears splitter/ch0, and grabber receives or publishes only grabber/audio", result.stderr


@pytest.mark.parametrize("hosted", [False, True], ids=["default", "vad_in_grabber"])
def test_esiaf_run_runs_the_vad_in_the_grabber_when_asked(launch, speech_48k, hosted):
    run = launch("--input", str(speech_48k), "--grammar", "robocup", "--without", "emotion,gender,voiceid", "--json",
                 *(["--vad-in-grabber"] if hosted else []))

    def alive() -> dict[str, dict]:
        listed = httpx.get(f"{run.url}/components", headers=run.headers, timeout=5).json()["items"]
        return {c["name"]: c for c in listed if c["status"] == "alive"}
    components = poll(lambda: (found := alive()).keys() >= {"grabber", "vad", "asr"} and found, timeout_s=60)
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=60)
    heard = [normalise(line["anchor"]["speech"]["hypotheses"][0]["text"]) for line in run.lines
             if line.get("type") == "fused_result"]
    assert heard == [normalise(t["text"]) for t in TRUTH], run.describe()
    assert (components["vad"]["pid"] == components["grabber"]["pid"]) is hosted
    assert components["vad"]["component_id"] != components["grabber"]["component_id"]


def test_vad_in_grabber_is_refused_where_one_grabber_does_not_feed_the_vad(tmp_path, speech_48k):
    second = tmp_path / "second.wav"
    second.write_bytes(speech_48k.read_bytes())
    result = esiaf_run("--input", str(speech_48k), "--input", str(second), "--vad-in-grabber", "--workdir",
                       str(tmp_path / "run"))
    assert_clear(result, "--vad-in-grabber: not possible here: several inputs play at once")

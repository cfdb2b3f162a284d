"""``esiaf run``: which analysers it starts (``--without``), and input files of any rate, sample
type and channel count."""
from __future__ import annotations

import json
import os
import signal

import httpx
import numpy as np
import pytest
import soundfile

from esiaf.tools.testing import REPO, normalise, poll
from tests.test_bad_input import assert_clear, esiaf_run

pytestmark = pytest.mark.e2e
SCENE = REPO / "examples" / "robocup_scene.flac"
TRUTH = json.loads(SCENE.with_suffix(".json").read_text())["utterances"][:2]
FEATURES = "ComParE_2016@16000"  # what the bundled emotion and gender models classify


def first_two_questions() -> tuple[np.ndarray, int]:
    """The demo scene's first two questions (0° and 90°), all four microphones, float in [-1, 1]."""
    mics, rate = soundfile.read(str(SCENE), dtype="float32", frames=int((TRUTH[-1]["end_s"] + 1.0) * 16000))
    return mics, rate


def fused_results(run) -> list[dict]:
    return [line for line in run.lines if line.get("type") == "fused_result"]


def test_without_leaves_the_analysers_out_and_nothing_waits_for_them(launch, tmp_path):
    mics, rate = first_two_questions()
    scene = tmp_path / "two.flac"
    soundfile.write(str(scene), mics, rate, subtype="PCM_16")
    run = launch("--input", str(scene), "--array", "respeaker4", "--grammar", "robocup", "--without",
                 "emotion,gender,voiceid", "--fast", "--json", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    items = httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]
    components = {c["name"] for c in items}
    assert {"asr", "vad", "beamformer", "denoiser", "ssl"} <= components, components
    assert not components & {"emotion", "gender", "voiceid", "splitter"}, components
    # grabber -> ssl -> beamformer -> vad -> denoiser -> asr
    inputs = {c["name"]: c["inputs"][0]["topic"] for c in items if c["inputs"]}
    assert [inputs[name] for name in ("vad", "denoiser", "asr")] == \
        ["beamformer/audio", "vad/speech", "denoiser/speech"], inputs
    fusions = httpx.get(f"{run.url}/fusions", headers=run.headers).json()
    default = {"ssl", "emotion", "gender", "voice_id"}
    assert any(set(f["fuse"]) == default for f in fusions["items"]), fusions
    fused = fused_results(run)
    assert [normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused] == \
        [normalise(t["text"]) for t in TRUTH]
    for f in fused:
        # published as soon as asr and ssl were done: no wait for analysers that are not running
        assert f["completion"] == "complete" and not f["missing_components"], f
        assert {kind for kind, results in f["results"].items() if results} == {"ssl"}, f["results"]
        assert f["aggregates"]["ssl"], f
        assert not (f["aggregates"].get("emotion") or f["aggregates"].get("gender") or f["aggregates"].get("voice_id"))


def test_pocketsphinx_and_voiceid_hear_the_denoiser_emotion_and_gender_the_vad(launch, tmp_path):
    mics, rate = first_two_questions()
    mono = tmp_path / "two.wav"
    soundfile.write(str(mono), mics[:, 0], rate, subtype="PCM_16")
    run = launch("--input", str(mono), "--grammar", "robocup", "--fast", "--json", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    items = httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]
    inputs = {c["name"]: c["inputs"][0]["topic"] for c in items if c["inputs"]}
    assert inputs == {"vad": "grabber/audio", "denoiser": "vad/speech", "asr": "denoiser/speech",
                      "voiceid": "denoiser/speech", "emotion": "vad/speech", "gender": "vad/speech"}, inputs
    fused = fused_results(run)
    assert [normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused] == \
        [normalise(t["text"]) for t in TRUTH]
    assert all(f["completion"] == "complete" and f["aggregates"]["voice_id"] for f in fused), fused


def test_a_stereo_44_1_khz_float_file_is_converted_and_channel_0_heard(launch, tmp_path):
    """The grabber sends the file as it is; the SDK converts it to the VAD's 16 kHz int16; without
    --array the splitter passes channel 0 on (and the launcher says so)."""
    import soxr
    mics, rate = first_two_questions()
    stereo = soxr.resample(np.stack([mics[:, 0], np.zeros_like(mics[:, 0])], axis=1), rate, 44100)
    path = tmp_path / "stereo.wav"
    soundfile.write(str(path), stereo.astype(np.float32), 44100, subtype="FLOAT")
    run = launch("--input", str(path), "--grammar", "robocup", "--without", "emotion,gender,voiceid", "--fast",
                 "--json")
    assert run.process.wait(timeout=150) == 0, "".join(run.stderr)
    assert any("has 2 channels and no --array: the analysers hear channel 0" in line for line in run.stderr), \
        run.stderr
    fused = fused_results(run)
    assert [normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused] == \
        [normalise(t["text"]) for t in TRUTH]
    start_ns = next(line for line in run.lines if line.get("type") == "stream_start")["start_ns"]
    for f, t in zip(fused, TRUTH, strict=True):  # capture times stay those of the file, whatever its rate
        assert abs((f["anchor"]["span"]["start_ns"] - start_ns) / 1e9 - t["start_s"]) < 0.3


def test_no_beamformer_no_denoiser_and_the_energy_vad_give_the_old_wiring(launch, tmp_path):
    mics, rate = first_two_questions()
    scene = tmp_path / "two.flac"
    soundfile.write(str(scene), mics, rate, subtype="PCM_16")
    run = launch("--input", str(scene), "--array", "respeaker4", "--grammar", "robocup", "--without",
                 "emotion,gender,voiceid", "--fast", "--json", "--serve", "--no-beamformer", "--vad", "energy",
                 "--denoiser", "off")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    components = httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]
    names = {c["name"] for c in components}
    assert {"asr", "vad", "splitter", "ssl"} <= names and not names & {"beamformer", "denoiser"}, names
    vad = next(c for c in components if c["name"] == "vad")
    assert vad["stats"]["info"]["backend"] == "energy" and vad["inputs"][0]["topic"] == "splitter/ch0", vad
    asr = next(c for c in components if c["name"] == "asr")
    assert asr["inputs"][0]["topic"] == "vad/speech", asr
    fused = fused_results(run)
    assert [normalise(f["anchor"]["speech"]["hypotheses"][0]["text"]) for f in fused] == \
        [normalise(t["text"]) for t in TRUTH]
    assert all(f["anchor"]["speech"] and f["aggregates"]["ssl"] for f in fused)


@pytest.mark.parametrize("without, message", [
    ("emotion,voice", "--without takes analysers separated by commas (ssl, emotion, gender, voiceid), not voice"),
    ("asr", "not asr"),
])
def test_without_names_only_analysers(tmp_path, without, message):
    result = esiaf_run("--input", str(SCENE), "--without", without, "--workdir", str(tmp_path))
    assert result.returncode == 2
    assert_clear(result, message)


def test_an_empty_file_is_refused(tmp_path):
    empty = tmp_path / "empty.wav"
    soundfile.write(str(empty), np.zeros((0, 1), dtype="int16"), 48000)
    assert_clear(esiaf_run("--input", str(empty), "--workdir", str(tmp_path)), "empty.wav holds no audio")


def analysers_of(run) -> dict[str, dict]:
    components = httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]
    return {c["name"]: c for c in components if c["status"] == "alive" and c["name"] in ("emotion", "gender")}


def labels(run, kind: str) -> list[list[tuple]]:
    """Per fused line, the ``kind`` results in it: label and probabilities."""
    return [[(r[kind]["label"], r[kind]["class_probabilities"]) for r in f["results"].get(kind) or []]
            for f in fused_results(run)]


def test_gender_is_a_guest_of_emotion_unless_apart_and_the_results_are_the_same(launch, tmp_path):
    """By default gender runs in emotion's process, each utterance's features computed once for both;
    --apart runs them as two processes, each computing its own, with the same results."""
    mics, rate = first_two_questions()
    mono = tmp_path / "two.wav"
    soundfile.write(str(mono), mics[:, 0], rate, subtype="PCM_16")
    runs = {}
    for mode in ("hosted", "apart"):
        run = launch("--input", str(mono), "--grammar", "robocup", "--without", "voiceid", "--fast", "--json",
                     "--serve", *(["--apart"] if mode == "apart" else []))
        run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
        fused = fused_results(run)
        assert len(fused) == len(TRUTH), fused
        for f in fused:
            assert f["completion"] == "complete" and not f["missing_components"], f
            assert f["aggregates"]["emotion"] and f["aggregates"]["gender"], f
        analysed = sum(len(f["results"]["emotion"]) for f in fused)
        components = poll(lambda run=run, n=analysed: (c := analysers_of(run)) and all(
            c[name]["stats"]["info"].get("analysed") == n for name in ("emotion", "gender")) and c, timeout_s=10)
        runs[mode] = run, components, analysed
        run.stop()
    (hosted, together, analysed), (apart, alone, _) = runs["hosted"], runs["apart"]
    assert together["emotion"]["pid"] == together["gender"]["pid"], together
    assert together["emotion"]["stats"]["info"]["guests"] == ["gender"]
    for name in ("emotion", "gender"):
        assert together[name]["stats"]["info"]["features"] == {FEATURES: {"computed": analysed, "reused": analysed}}
        assert alone[name]["stats"]["info"]["features"] == {FEATURES: {"computed": analysed, "reused": 0}}
    assert alone["emotion"]["pid"] != alone["gender"]["pid"]
    for kind in ("emotion", "gender"):
        assert labels(hosted, kind) == labels(apart, kind)


def test_without_gender_emotion_runs_alone(launch, tmp_path):
    mics, rate = first_two_questions()
    mono = tmp_path / "two.wav"
    soundfile.write(str(mono), mics[:, 0], rate, subtype="PCM_16")
    run = launch("--input", str(mono), "--grammar", "robocup", "--without", "gender,voiceid", "--fast", "--json",
                 "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    fused = fused_results(run)
    assert len(fused) == len(TRUTH), fused
    for f in fused:
        assert f["completion"] == "complete" and not f["missing_components"], f
        assert f["aggregates"]["emotion"] and not f["aggregates"].get("gender"), f
    analysed = sum(len(f["results"]["emotion"]) for f in fused)
    components = poll(lambda: (c := analysers_of(run)) and c["emotion"]["stats"]["info"].get("analysed") == analysed
                      and c, timeout_s=10)
    assert set(components) == {"emotion"}
    assert "guests" not in components["emotion"]["stats"]["info"]
    assert components["emotion"]["stats"]["info"]["features"] == {FEATURES: {"computed": analysed, "reused": 0}}


def test_a_killed_host_comes_back_with_its_guest(launch, tmp_path):
    """The process of emotion and its guest gender dies: esiaf run reports both dead at once and
    restarts the process, which registers both again."""
    mics, rate = first_two_questions()
    mono = tmp_path / "two.wav"
    soundfile.write(str(mono), mics[:, 0], rate, subtype="PCM_16")
    run = launch("--input", str(mono), "--grammar", "robocup", "--without", "voiceid", "--fast", "--json", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=150)
    before = analysers_of(run)
    pid = before["emotion"]["pid"]
    assert before["gender"]["pid"] == pid
    os.kill(pid, signal.SIGKILL)

    def listed() -> dict[str, list[dict]]:
        items = httpx.get(f"{run.url}/components?include_dead=true", headers=run.headers).json()["items"]
        return {name: [c for c in items if c["name"] == name] for name in ("emotion", "gender")}
    poll(lambda: all(any(c["component_id"] == before[name]["component_id"] and c["status"] == "dead"
                         for c in listed()[name]) for name in ("emotion", "gender")), timeout_s=2)
    after = poll(lambda: (c := analysers_of(run)) and len(c) == 2 and c["emotion"]["pid"] != pid and c,
                 timeout_s=60)
    assert after["gender"]["pid"] == after["emotion"]["pid"], after
    assert "service emotion killed by SIGKILL" in "".join(run.stderr)

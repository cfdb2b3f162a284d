"""One enrolment must not switch voice identity off for everyone, nor cost the orchestrator
gigabytes: a WAV with a NaN sample, a name of 10,001 characters or with a terminal escape, the
1,001st voice, a header that says 1 Hz or 1,000,003 Hz, a minute and more of audio — each is a 4xx
with its reason, the orchestrator's memory stays put, and a result the orchestrator would refuse
is never sent by the SDK: counted, with its reason, in ``GET /components``.

The orchestrator as a process with its SQLite file, real HTTP; the SDK's components on real
sockets; the voiceid analyser with its real encoder."""
from __future__ import annotations

import io
import time
from urllib.parse import quote

import numpy as np
import psutil
import pytest
import zmq
from scipy.io import wavfile
from test_component import run_on

from bench.bad_cli import wav_header
from esiaf.result_checks import check_result
from esiaf.results import make_result
from esiaf.tools.testing import Orchestrator, poll, shared_data
from esiaf_services.orchestrator.store.voices import MAX_VOICES
from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body

S = 1_000_000_000
ARCTIC = "speech/cmu_arctic/cmu_arctic_us_aew_a0001.wav"


@pytest.fixture
def zctx():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


def wav(samples: np.ndarray, rate_hz: int) -> bytes:
    out = io.BytesIO()
    wavfile.write(out, rate_hz, samples)
    return out.getvalue()


def enrol_wav(orchestrator: Orchestrator, name: str, data: bytes):
    return orchestrator.http.post(f"/voices/{quote(name, safe='')}", files={"audio": ("a.wav", data)}, timeout=60)


def test_hostile_wavs_and_names_are_4xx_with_the_reason_and_cost_no_memory(orchestrator):
    running = orchestrator  # the root conftest's: the real process, its SQLite file
    rate, speech = wavfile.read(shared_data(ARCTIC))
    assert enrol_wav(running, "Anna", wav(speech, rate)).status_code == 200
    rss_before = psutil.Process(running.process.pid).memory_info().rss
    with_nan = speech.astype(np.float32) / 32768
    with_nan[len(with_nan) // 2] = np.nan
    cases = {
        "a float WAV with one NaN sample": (enrol_wav(running, "Ben", wav(with_nan, rate)), 422, "NaN"),
        "a header saying 1 Hz (444 bytes)": (enrol_wav(running, "Ben", wav_header(1)), 422, "1 Hz"),
        "a header saying 1,000,003 Hz (600 KB)": (
            enrol_wav(running, "Ben", wav_header(1_000_003, samples=300_000)), 422, "1000003 Hz"),
        "61 s at 8 kHz": (enrol_wav(running, "Ben", wav(np.zeros(61 * 8000, np.int16), 8000)), 422, "at most 60 s"),
        "a name of 10,001 characters": (enrol_wav(running, "x" * 10_001, wav(speech, rate)), 422, "at most 200"),
        "a name with a terminal escape": (
            enrol_wav(running, "Eve\x1b[2K\rAnna", wav(speech, rate)), 422, "control character"),
        "the voiceid's label for a segment it cannot tell": (enrol_wav(running, "unknown", wav(speech, rate)), 422,
                                                              "cannot tell"),
    }
    for what, (reply, status, reason) in cases.items():
        assert reply.status_code == status and reason in reply.json()["detail"], (what, reply.status_code, reply.text)
    grown_mb = (psutil.Process(running.process.pid).memory_info().rss - rss_before) / 2**20
    assert grown_mb < 50, grown_mb
    voices = running.http.get("/voices").json()["voices"]
    assert [v["name"] for v in voices] == ["Anna"]  # nothing of the refused ones stored


def test_the_thousand_and_first_voice_is_a_409_and_the_others_still_enrol(orchestrator, zctx):
    running = orchestrator
    """1,000 voices enrolled from one stored utterance's embedding (JSON enrolment: no encoding), then
    a new name is refused with the reason while a known one still takes more embeddings."""
    fake = FakeComponent(zctx, running.http, component_body("voiceid", kind="voice_id", inputs=["in"]))
    try:
        embedding = np.ones(256, np.float32) / 16.0
        t1 = time.time_ns()
        fake.emit("voice_id", (t1 - S, t1), voice_id={"label": "voice-1", "probability": 0.9,
                                                     "class_probabilities": {}, "embedding": embedding.tolist()})
        poll(lambda: running.http.get("/results", params={"type": "voice_id"}).json()["items"], timeout_s=10)
        span = {"stream": "default", "start_ns": t1 - S, "end_ns": t1}
        for i in range(MAX_VOICES):
            reply = running.http.post(f"/voices/person-{i:04d}", json=span)
            assert reply.status_code == 200, (i, reply.text)
        refused = running.http.post("/voices/one-too-many", json=span)
        assert refused.status_code == 409 and "delete one first" in refused.json()["detail"]
        assert running.http.post("/voices/person-0007", json=span).status_code == 200  # a known voice: more
        assert len(running.http.get("/voices").json()["voices"]) == MAX_VOICES
    finally:
        fake.close()


def test_voiceid_with_a_thousand_voices_reports_a_bounded_top_k_the_orchestrator_takes():
    from esiaf.testing import run_analyser
    from esiaf_services.voiceid.scoring import VoiceBook
    from esiaf_services.voiceid.service import VoiceId, VoiceIdSettings

    analyser = VoiceId(VoiceIdSettings(name="voiceid", voices_wait_s=1.0, orchestrator_url="http://127.0.0.1:9"))
    rng = np.random.default_rng(1)
    analyser.book = VoiceBook({f"person-{i:04d}": rng.standard_normal((1, 256)).astype(np.float32)
                               for i in range(1001)})
    emitted = run_analyser(analyser, shared_data(ARCTIC), spans=[(0.0, 3.0)])
    assert len(emitted) == 1 and analyser.context.results_invalid == 0
    payload = emitted[0].payload
    assert 1 <= len(payload["class_probabilities"]) <= 10
    assert all(0.0 <= p <= 1.0 for p in payload["class_probabilities"].values())
    result = make_result("voiceid", "voice_id", "s", (0, 3 * S), 1, voice_id=payload)
    check_result(result)  # what the orchestrator checks on arrival


def test_a_result_the_orchestrator_would_refuse_is_not_sent_but_counted_with_its_reason(orchestrator):
    from test_component import Source, start

    source, thread = start(Source, orchestrator.url)
    try:
        poll(lambda: orchestrator.component("source"), timeout_s=10)
        now = time.time_ns()

        def emit(c):
            c.emit("vad", (now - S, now), stream_id="s", vad={"probability": float("nan")})
            c.emit("emotion", (now - S, now), stream_id="s", emotion={
                "label": "a", "probability": 0.5, "class_probabilities": {f"c{i}": 0.0 for i in range(1001)}})
            c.emit("vad", (now - S, now), stream_id="s", vad={"probability": 0.9})

        assert run_on(source, emit).wait(10)
        stats = poll(lambda: (s := orchestrator.component("source")["stats"]).get("results_invalid") == 2
                     and s.get("results_sent") == 1 and s, timeout_s=10)  # one heartbeat may come between
        assert "more than 1000" in stats["results_invalid_reason"]
        stored = poll(lambda: orchestrator.http.get("/results", params={"stream": "s"}).json()["items"],
                      timeout_s=10)
        assert [r["vad"]["probability"] for r in stored] == [0.9]
    finally:
        source.stop()
        thread.join(timeout=10)

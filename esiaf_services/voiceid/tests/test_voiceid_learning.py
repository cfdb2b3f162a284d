"""Voices that learn, and embeddings kept per encoder, through the orchestrator as a process (real
SQLite file, real HTTP) and the voiceid's analyser with its real encoders."""
from __future__ import annotations

import io
import queue
import sqlite3
import threading
import time

import numpy as np
import pytest
import soundfile
from scipy.io import wavfile

from esiaf import AudioFormat, Component, ComponentSettings
from esiaf.tools.testing import Orchestrator, poll, shared_data
from esiaf_services.orchestrator.settings import OrchestratorSettings
from esiaf_services.orchestrator.store.voices import MAX_LEARNT_PER_VOICE
from esiaf_services.voiceid.service import VoiceId, VoiceIdSettings

AEW = "speech/cmu_arctic/cmu_arctic_us_aew_a000{}.wav"
COPIES = OrchestratorSettings().enrolment_room_copies  # a WAV's room copies by default (0), enrolled beside it


@pytest.fixture
def running(orchestrator):
    """The root conftest's orchestrator (a process with its SQLite file), under this module's name for it."""
    return orchestrator


def wav_bytes(samples: np.ndarray, rate_hz: int = 16000) -> bytes:
    out = io.BytesIO()
    wavfile.write(out, rate_hz, samples)
    return out.getvalue()


def speech(n: int) -> np.ndarray:
    samples, rate = soundfile.read(shared_data(AEW.format(n)), dtype="float32")
    assert rate == 16000
    return samples


def enrol(orchestrator: Orchestrator, name: str, samples: np.ndarray):
    return orchestrator.http.post(f"/voices/{name}", files={"audio": ("a.wav", wav_bytes(samples))}, timeout=120)


def voice(orchestrator: Orchestrator, name: str) -> dict:
    return next(v for v in orchestrator.http.get("/voices").json()["voices"] if v["name"] == name)


@pytest.fixture
def with_copies(tmp_path):
    """An orchestrator that enrols 2 room copies of each WAV (enrolment_room_copies: 2)."""
    orchestrator = Orchestrator(tmp_path, env={"ESIAF_ORCHESTRATOR_ENROLMENT_ROOM_COPIES": "2"})
    yield orchestrator
    orchestrator.close()


def test_a_wav_is_enrolled_for_every_encoder_with_its_room_copies_and_each_voiceid_gets_only_its_own(with_copies):
    running, copies = with_copies, 2
    reply = enrol(running, "Anna", speech(1))
    assert reply.status_code == 200 and sorted(reply.json()["encoders"]) == ["dvector", "fused", "ge2e"], reply.text
    assert reply.json()["added"] == 1 and reply.json()["room_copies"] == copies
    listed = voice(running, "Anna")
    assert listed["encoders"] == {m: {"enrolled": 1 + copies, "learnt": 0} for m in ("ge2e", "dvector", "fused")}
    assert listed["sources"] == ["wav", "wav-room"]
    for model, size in (("ge2e", 256), ("dvector", 256), ("fused", 512)):
        voices = running.http.get("/voices", params={"embeddings": 1, "encoder": model}).json()["voices"]
        assert voices[0]["embedding_sources"] == ["wav"] + ["wav-room"] * copies
        embeddings = np.array(voices[0]["embeddings"], np.float32)
        assert embeddings.shape == (1 + copies, size)
        cosines = embeddings[1:] @ embeddings[0]
        assert np.all(cosines < 0.999) and np.all(cosines > 0.3), cosines  # other sounds of the same voice
    old_client = running.http.get("/voices", params={"embeddings": 1}).json()["voices"]  # asks for no encoder
    assert [len(e) for e in old_client[0]["embeddings"]] == [256] * (1 + copies)  # GE2E's
    assert enrol(running, "Anna", speech(1)).json()["room_copies"] == copies  # the same WAV: the same copies
    again = running.http.get("/voices", params={"embeddings": 1, "encoder": "dvector"}).json()["voices"][0]
    np.testing.assert_array_equal(again["embeddings"][1 + copies:], again["embeddings"][:1 + copies])


def test_by_default_a_wav_is_enrolled_clean_alone(running):
    assert COPIES == 0  # the copies cost clean names at the calibrated thresholds (docs/benchmarks.md)
    reply = enrol(running, "Anna", speech(1))
    assert reply.status_code == 200 and reply.json()["room_copies"] == 0, reply.text
    listed = voice(running, "Anna")
    assert listed["sources"] == ["wav"] and listed["encoders"]["dvector"] == {"enrolled": 1, "learnt": 0}


def test_noise_and_a_short_word_are_refused_with_the_reason(running):
    rng = np.random.default_rng(0)
    noise = (0.1 * rng.standard_normal(3 * 16000)).astype(np.float32)
    refused = enrol(running, "Noise", noise)
    assert refused.status_code == 422 and "no speech found" in refused.json()["detail"], refused.text
    word = np.zeros(2 * 16000, np.float32)
    first = speech(1)
    loud = np.flatnonzero(np.abs(first) > 0.1)[0]
    word[8000:8000 + 4800] = first[loud:loud + 4800]  # 0.3 s of speech in 2 s of silence
    refused = enrol(running, "Word", word)
    assert refused.status_code == 422 and "only 0.3" in refused.json()["detail"], refused.text
    assert running.http.get("/voices").json()["voices"] == []


def test_learnt_embeddings_are_bounded_forgotten_on_request_and_survive_a_restart(running):
    from esiaf.speech.speaker.encoders import shared_encoder
    assert enrol(running, "Anna", speech(1)).status_code == 200
    learnt = shared_encoder("dvector").embed(speech(2)).tolist()
    for _ in range(MAX_LEARNT_PER_VOICE + 3):
        reply = running.http.post("/voices/Anna/learnt", json={"encoder": "dvector", "embedding": learnt})
        assert reply.status_code == 200, reply.text
    assert reply.json()["dropped_oldest_learnt"] == 1  # the oldest learnt went, not the enrolled one
    anna = voice(running, "Anna")
    assert anna["encoders"]["dvector"] == {"enrolled": 1 + COPIES, "learnt": MAX_LEARNT_PER_VOICE}
    assert anna["encoders"]["ge2e"] == {"enrolled": 1 + COPIES, "learnt": 0}
    refused = running.http.post("/voices/Nobody/learnt", json={"encoder": "dvector", "embedding": learnt})
    assert refused.status_code == 404  # learning never creates a voice
    wrong = running.http.post("/voices/Anna/learnt", json={"encoder": "fused", "embedding": learnt})
    assert wrong.status_code == 422 and "512" in wrong.text
    running.process.terminate()  # as a service manager stops it
    running.process.wait(timeout=30)
    running.start()  # the same port and database file
    assert voice(running, "Anna")["encoders"]["dvector"] == {"enrolled": 1 + COPIES, "learnt": MAX_LEARNT_PER_VOICE}
    forgotten = running.http.post("/voices/Anna/forget-learnt")
    assert forgotten.status_code == 200 and forgotten.json()["forgotten"] == MAX_LEARNT_PER_VOICE
    anna = voice(running, "Anna")
    assert anna["learnt"] == 0 and anna["enrolled"] == 1 + COPIES and "learnt" not in anna["sources"]
    assert running.http.post("/voices/Nobody/forget-learnt").status_code == 404


def test_a_database_from_before_the_encoder_column_keeps_its_voices_as_ge2e(tmp_path):
    db = sqlite3.connect(tmp_path / "o.db")
    db.executescript("""CREATE TABLE voices (id INTEGER PRIMARY KEY, name TEXT NOT NULL, embedding BLOB NOT NULL,
                        source TEXT NOT NULL, added_ns INTEGER NOT NULL);""")
    db.execute("INSERT INTO voices (name, embedding, source, added_ns) VALUES ('Old', ?, 'wav', 1)",
               (np.full(256, 1 / 16, "<f4").tobytes(),))
    db.commit()
    db.close()
    orchestrator = Orchestrator(tmp_path)
    try:
        old = voice(orchestrator, "Old")
        assert old["encoders"] == {"ge2e": {"enrolled": 1, "learnt": 0}}
        assert orchestrator.http.get("/voices", params={"embeddings": 1, "encoder": "dvector"}).json()["voices"][0][
            "embeddings"] == []  # never given to a voiceid of another encoder
    finally:
        orchestrator.close()


TOKEN = "learning-token-0123456789abcdef"


def test_the_voiceid_learns_a_confident_utterance_but_not_a_quiet_or_overlapped_one(tmp_path, monkeypatch):
    """Each case is identified as Anna; only the loud, not overlapped one is posted as learnt, with the
    token the orchestrator asks for (ESIAF_TOKEN, as every service has it)."""
    running = Orchestrator(tmp_path, env={"ESIAF_TOKEN": TOKEN})
    try:
        assert running.http.get("/voices").status_code == 401  # no token, no voices
        running.http.headers["Authorization"] = f"Bearer {TOKEN}"
        monkeypatch.setenv("ESIAF_TOKEN", TOKEN)  # the voiceid's requests carry it
        identify_and_learn(running)
    finally:
        running.close()


def identify_and_learn(running: Orchestrator) -> None:
    from esiaf.api_client import OrchestratorHTTP
    from esiaf.testing import run_analyser

    assert enrol(running, "Anna", np.concatenate([speech(1), speech(3)])).status_code == 200

    def learnt() -> int:
        return voice(running, "Anna")["encoders"]["dvector"]["learnt"]

    clip = speech(2)  # 3.4 s, RMS about -21 dBFS
    rms_db = 20 * np.log10(float(np.sqrt(np.mean(clip.astype(np.float64) ** 2))))
    for what, gate, overlapped in (("quieter than learn_min_dbfs", {"learn_min_dbfs": rms_db + 1}, False),
                                   ("shorter than learn_min_speech_ms", {"learn_min_speech_ms": 5000.0}, False),
                                   ("overlapping playback", {}, True), ("confident", {}, False)):
        service = VoiceId(VoiceIdSettings(name="voiceid", model="dvector", voices_wait_s=1.0, learn=True,
                                          orchestrator_url=running.url, **gate))
        if overlapped:  # the robot spoke during the utterance's last second (run_analyser's stream: "test")
            assert service.played is not None
            service.played.add_span("test", (clip.size // 16 - 1000) * 1_000_000, clip.size // 16 * 1_000_000)
        with OrchestratorHTTP(running.url) as client:
            service.refresh_voices(client)  # the enrolled voices before the first utterance
        emitted = run_analyser(service, (clip, 16000), spans=[(0.0, clip.size / 16000)])
        assert len(emitted) == 1 and emitted[0].payload["label"] == "Anna", (what, emitted)
        if what == "confident":
            poll(lambda: learnt() == 1, timeout_s=20)
        else:
            assert learnt() == 0, what


RATE = 16000
NS = 1_000_000_000
CHUNK = 800  # 50 ms


class Robot(Component):
    """The VAD's segments (``vad/speech``) and the player's audio (``player/audio``) of stream s1, in 50 ms
    chunks on the same capture clock, each batch when the test says so."""

    service = "robot"

    def __init__(self, settings):
        super().__init__(settings)
        self.add_output("vad/speech", AudioFormat(RATE, "int16"))
        self.add_output("player/audio", AudioFormat(RATE, "int16"))
        self.batches: queue.Queue[tuple[str, np.ndarray, float, bool]] = queue.Queue()

    def produce(self):
        while not self.stopping:
            try:
                topic, samples, start_s, segment = self.batches.get_nowait()
            except queue.Empty:
                self.sleep_until(time.monotonic() + 0.02)  # the node's own work (its state) meanwhile
                continue
            pcm = np.clip(np.rint(samples * 32767), -32768, 32767).astype(np.int16)
            first_ns = round(start_s * NS)
            last_ns = first_ns + len(pcm) * NS // RATE
            for first in range(0, len(pcm), CHUNK):
                piece = pcm[first:first + CHUNK]
                start_ns = first_ns + first * NS // RATE
                end_ns = start_ns + len(piece) * NS // RATE
                ended = segment and first + CHUNK >= len(pcm)
                self.publish(topic, piece[:, None], start_ns, end_ns, segmentation_ended=ended,
                             segment=(first_ns, last_ns) if ended else None)


class VoiceIdComponent(VoiceId, Component):
    """The voiceid as its service runs it: a component on real sockets."""


def test_an_utterance_overlapping_the_robots_playback_is_not_learnt(running):
    """Over real sockets: the player's audio (the robot's voice, then silence) and two of Anna's confident
    utterances; the one whose capture span overlaps the robot's voice is identified but not learnt, the
    one heard while the player sends only silence is learnt."""
    assert enrol(running, "Anna", np.concatenate([speech(1), speech(3)])).status_code == 200
    robot = Robot(ComponentSettings(name="robot", orchestrator_url=running.url, stream_id="s1"))
    voiceid = VoiceIdComponent(VoiceIdSettings(name="voiceid", model="dvector", voices_wait_s=1.0, learn=True,
                                               orchestrator_url=running.url, stream_id="s1"))
    threads = [threading.Thread(target=c.run, daemon=True) for c in (robot, voiceid)]
    for thread in threads:
        thread.start()
    try:
        poll(lambda: "Anna" in voiceid.book.voices, timeout_s=60)
        poll(lambda: all(robot.output_stats[t].subscribers for t in ("vad/speech", "player/audio")), timeout_s=30)
        robot_voice, _ = soundfile.read(shared_data("speech/cmu_arctic/cmu_arctic_us_axb_a0004.wav"), dtype="float32")
        clip = speech(2)
        robot.batches.put(("player/audio", 0.5 * robot_voice / np.max(np.abs(robot_voice)), 1.0, False))
        played_until = 1.0 + robot_voice.size / RATE
        robot.batches.put(("player/audio", np.zeros(12 * RATE, np.float32), played_until, False))  # silence
        chunks = -(-robot_voice.size // CHUNK) + 12 * RATE // CHUNK
        poll(lambda: voiceid.input_stats["player/audio"].received == chunks,  # the player publishes ahead of
             timeout_s=20)  # what the microphones hear: all of it is in before the utterances
        assert voiceid.played is not None and len(voiceid.played.spans["s1"]) >= 1
        assert voiceid.played.spans["s1"][-1][1] <= played_until * NS  # its silence is not playing
        robot.batches.put(("vad/speech", clip, 2.0, True))  # overlaps the robot's voice
        poll(lambda: voiceid.analysed == 1, timeout_s=30)
        assert voiceid.info.get("learning", 0) == 0
        robot.batches.put(("vad/speech", clip, played_until + 5.0, True))  # only the player's silence then
        poll(lambda: voiceid.analysed == 2, timeout_s=30)
        assert voiceid.info.get("learning", 0) == 1
        poll(lambda: voice(running, "Anna")["encoders"]["dvector"]["learnt"] == 1, timeout_s=20)
        # the voiceid hears of it and keeps it apart from the enrolled one (embedding_sources)
        poll(lambda: len(voiceid.book.learnt.get("Anna", ())) == 1, timeout_s=20)
        assert len(voiceid.book.voices["Anna"]) == 1 + COPIES  # the WAV and its room copies
        results = poll(lambda: running.http.get("/results", params={"type": "voice_id"}).json()["items"][1:] and
                       running.http.get("/results", params={"type": "voice_id"}).json()["items"], timeout_s=10)
        assert [r["voice_id"]["label"] for r in results] == ["Anna", "Anna"]  # both identified, one learnt
    finally:
        for component in (robot, voiceid):
            component.stop()
        for thread in threads:
            thread.join(timeout=10)

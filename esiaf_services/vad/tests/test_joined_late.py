"""A vad that joins a stream after its start (started, or restarted after a crash, while the stream went
on) never starts a segment in the middle of speech: its end alone would be recognised as a wrong sentence.
The Silero backend on the example's questions."""
import json
from typing import Any

import soundfile

from esiaf import Audio, AudioFormat
from esiaf.results import SPEECH_START
from esiaf.tools.testing import REPO
from esiaf_services.vad.service import Vad, VadSettings

EXAMPLE = REPO / "examples" / "robocup_questions.wav"
NS = 1_000_000_000
RATE = 16000
CHUNK = 800  # 50 ms


class Recording(Vad):
    """The vad service with the spans of its VAD results and speech starts noted instead of anything sent."""

    def __init__(self, settings: VadSettings):
        super().__init__(settings)
        self.found: list[tuple[int, int]] = []
        self.starts: list[tuple[int, int]] = []

    def publish(self, *args: Any, **kwargs: Any) -> int:
        return 1

    def emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None, **payload: Any) -> Any:
        if kind == "vad":
            self.found.append(span)
        elif kind == SPEECH_START:
            self.starts.append(span)


def segments(first_s: float, last_s: float, first_sequence: int) -> list[tuple[int, int]]:
    """The speech spans a new vad finds from ``first_s`` of the example on, its first chunk numbered
    ``first_sequence`` by the grabber."""
    return played(first_s, last_s, first_sequence).found


def played(first_s: float, last_s: float, first_sequence: int, **settings: Any) -> Recording:
    """A new vad (``settings``) that heard the example from ``first_s`` to ``last_s``."""
    vad = Recording(VadSettings(**settings))
    vad.setup()
    samples, rate = soundfile.read(str(EXAMPLE), dtype="int16")
    assert rate == RATE
    fmt = AudioFormat(RATE, "int16", channels=1)
    for n, start in enumerate(range(int(first_s * RATE), int(last_s * RATE), CHUNK)):
        chunk = samples[start:start + CHUNK]
        vad.on_audio(Audio("grabber/audio", "s", "grabber", first_sequence + n, start * NS // RATE,
                           (start + len(chunk)) * NS // RATE, fmt, chunk.tobytes()))
    return vad


def test_a_vad_joining_mid_utterance_waits_for_silence_and_one_there_from_the_start_does_not():
    sentences = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"]
    second, third = sentences[1], sentences[2]
    joined_at = (second["start_s"] + second["end_s"]) / 2  # in the middle of the second question
    late = segments(joined_at, third["end_s"] + 1.0, first_sequence=int(joined_at * RATE) // CHUNK + 1)
    assert len(late) == 1 and abs(late[0][0] / NS - third["start_s"]) < 0.3, late  # the third question only
    # the same audio as a stream's start (a file that begins mid-sentence): its first speech is a segment
    whole = segments(joined_at, third["end_s"] + 1.0, first_sequence=1)
    assert len(whole) == 2 and whole[1] == late[0], whole

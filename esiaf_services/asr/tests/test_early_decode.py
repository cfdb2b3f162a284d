"""Whisper decodes an utterance during the vad's hang-over: the real vad (Silero) segments the example's
questions and marks how far it has heard speech (``meta.speech_until_ns``); the real asr (Whisper, the
robocup closed set) decodes each question once that mark is ``early_decode_ms`` behind, before the vad
closes the segment, and publishes that decode at the close."""
import itertools
import json
from typing import Any

import pytest
import soundfile

from esiaf import Audio, AudioFormat
from esiaf.tools.testing import REPO, normalise
from esiaf_services.asr.service import Asr, AsrSettings
from esiaf_services.vad.service import Vad, VadSettings

EXAMPLE = REPO / "examples" / "robocup_questions.wav"
NS = 1_000_000_000
RATE = 16000
CHUNK = 320  # 20 ms, as the grabber sends them
FORMAT = AudioFormat(RATE, "int16", channels=1)

pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")


class Passing(Vad):
    """The vad service with what it publishes kept as the asr would receive it."""

    def __init__(self, settings: VadSettings):
        super().__init__(settings)
        self.out: list[Audio] = []

    def publish(self, topic: str, audio: Any, start_ns: int, end_ns: int, *, stream_id: str | None = None,
                segmentation_ended: bool = False, segment: tuple[int, int] | None = None,
                speech_until_ns: int = 0, **_: Any) -> int:
        chunk = Audio(topic, stream_id or "s", "vad", len(self.out) + 1, start_ns, end_ns, FORMAT, bytes(audio))
        chunk.meta.segmentation_ended, chunk.meta.speech_until_ns = segmentation_ended, speech_until_ns
        if segment is not None:
            chunk.meta.segment.start_ns, chunk.meta.segment.end_ns = segment
        self.out.append(chunk)
        return len(self.out)

    def emit(self, *args: Any, **kwargs: Any) -> Any:
        return None


def vad_output(first_s: float, last_s: float) -> list[Audio]:
    vad = Passing(VadSettings())
    vad.setup()
    samples, rate = soundfile.read(str(EXAMPLE), dtype="int16")
    assert rate == RATE
    for n, start in enumerate(range(int(first_s * RATE), int(last_s * RATE), CHUNK)):
        chunk = samples[start:start + CHUNK]
        vad.on_audio(Audio("grabber/audio", "s", "grabber", n + 1, start * NS // RATE,
                           (start + len(chunk)) * NS // RATE, FORMAT, chunk.tobytes()))
    return vad.out


def recognise(chunks: list[Audio], early_decode_ms: float) -> tuple[list[str], list[int], Asr]:
    """The asr fed the vad's chunks: the texts it published, and how many early decodes it had made when
    each segment closed."""
    asr = Asr(AsrSettings(grammar="robocup", backend="whisper", whisper={"early_decode_ms": early_decode_ms}))
    asr.setup()
    texts: list[str] = []
    asr.emit = lambda kind, span, stream_id=None, **payload: (  # type: ignore[method-assign,assignment]
        texts.append(payload["speech"]["hypotheses"][0].text) if kind == "speech" else None)
    decoded_before_close = []
    for chunk in chunks:
        asr.on_audio(chunk)
        if chunk.segmentation_ended:
            decoded_before_close.append(asr.early_decodes)
            asr.on_segment_end(chunk)
    return texts, decoded_before_close, asr


def test_the_vad_marks_how_far_it_heard_speech_and_the_segment_ends_there():
    sentences = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"]
    chunks = vad_output(sentences[0]["start_s"] - 1.0, sentences[1]["end_s"] + 1.0)
    ends = [c for c in chunks if c.segmentation_ended]
    assert len(ends) == 2
    for end in ends:
        mine = [c for c in chunks if end.meta.segment.start_ns <= c.end_ns <= end.end_ns and not c.segmentation_ended]
        marks = [c.meta.speech_until_ns for c in mine]
        assert marks == sorted(marks) and all(0 < m <= c.end_ns for m, c in zip(marks, mine, strict=True))
        assert marks[-1] == end.meta.segment.end_ns  # the hang-over's chunks: speech last heard at its end
        assert end.end_ns - marks[-1] >= 350 * 1_000_000  # ... a hang-over later the segment closes


def test_whisper_decodes_during_the_hang_over_and_publishes_that_decode_at_the_close():
    sentences = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"]
    chunks = vad_output(sentences[0]["start_s"] - 1.0, sentences[2]["end_s"] + 1.0)
    texts, decoded_before_close, asr = recognise(chunks, 150.0)
    assert [normalise(t) for t in texts] == [normalise(s["text"]) for s in sentences[:3]]
    assert decoded_before_close[0] >= 1 and all(
        b > a for a, b in itertools.pairwise(decoded_before_close))
    assert asr.early_used == 3  # each question's result was decoded before its segment closed
    at_close, _, plain = recognise(chunks, 0.0)  # off: each segment decoded whole at its close
    assert at_close == texts and plain.early_decodes == plain.early_used == 0


def test_a_pause_within_an_utterance_is_decoded_early_and_that_decode_is_dropped():
    """Speech that goes on after a pause moves the vad's mark on: the decode made at the pause is not the
    utterance's result (it would lose the words after it)."""
    sentence = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"][1]  # What does CAPTCHA stands for?
    samples, _ = soundfile.read(str(EXAMPLE), dtype="int16")
    start, end = int((sentence["start_s"] - 0.3) * RATE), int((sentence["end_s"] + 0.45) * RATE)
    pause_at = int((sentence["start_s"] + 0.55) * RATE)  # after "what does": the vad heard 200 ms of silence
    speech_end_ns = int(sentence["end_s"] * NS)
    chunks = []
    for n, at in enumerate(range(start, end, CHUNK)):
        chunk = Audio("vad/speech", "s", "vad", n + 1, at * NS // RATE, (at + CHUNK) * NS // RATE, FORMAT,
                      samples[at:at + CHUNK].tobytes())
        in_pause = pause_at <= at < pause_at + int(0.2 * RATE)
        chunk.meta.speech_until_ns = pause_at * NS // RATE if in_pause else min(chunk.end_ns, speech_end_ns)
        chunks.append(chunk)
    chunks[-1].meta.segmentation_ended = True
    chunks[-1].meta.segment.start_ns, chunks[-1].meta.segment.end_ns = int(sentence["start_s"] * NS), speech_end_ns
    texts, decoded_before_close, asr = recognise(chunks, 150.0)
    assert [normalise(t) for t in texts] == [normalise(sentence["text"])]
    assert decoded_before_close == [2] and asr.early_used == 1  # at the pause (dropped) and at the end

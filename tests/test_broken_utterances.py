"""An utterance analyser whose open segment breaks off (its VAD killed and restarted: another publisher
carries on; or messages lost) says nothing about it, with the reason, and takes the next segment whole.
Before, the next segment was cut out of both at the wrong offsets: it came out empty ("too short")."""
from __future__ import annotations

from typing import Any

import numpy as np

from esiaf import Audio, AudioFormat
from esiaf.utterance import Utterance, UtteranceAnalyser, UtteranceSettings

RATE = 16000
NS = 1_000_000_000
CHUNK = 320  # 20 ms
FMT = AudioFormat(RATE, "int16", channels=1)


class Duration(UtteranceAnalyser):
    service = "duration"
    kind = "duration"

    def analyse(self, utterance: Utterance) -> dict[str, Any]:
        return {"value": utterance.duration_s}


def forward(analyser: Duration, publisher: str, first_s: float, last_s: float, ends: bool,
            skip: range = range(0)) -> None:
    """A tone from ``first_s`` to ``last_s`` in 20 ms chunks numbered from 1 (those in ``skip`` lost on
    the way), the last closing the segment if ``ends``."""
    tone = (8000 * np.sin(np.arange(int(last_s * RATE)) * 0.3)).astype(np.int16)
    starts = list(range(int(first_s * RATE), int(last_s * RATE), CHUNK))
    for sequence, start in enumerate(starts, start=1):
        if sequence in skip:
            continue
        chunk = tone[start:start + CHUNK]
        audio = Audio("vad/speech", "s", publisher, sequence, start * NS // RATE, (start + len(chunk)) * NS // RATE,
                      FMT, chunk.tobytes())
        if ends and start == starts[-1]:
            audio.meta.segmentation_ended = True
            audio.meta.segment.start_ns, audio.meta.segment.end_ns = round(first_s * NS), round(last_s * NS)
        analyser.on_audio(audio)
        if audio.meta.segmentation_ended:
            analyser.on_segment_end(audio)


def analyser_and_results() -> tuple[Duration, list[tuple[tuple[int, int], dict[str, Any]]]]:
    analyser = Duration(UtteranceSettings(name="duration"))
    emitted: list[tuple[tuple[int, int], dict[str, Any]]] = []
    analyser.emit = lambda kind, span, stream_id=None, **payload: emitted.append((span, payload))  # type: ignore[method-assign, assignment, misc]
    return analyser, emitted


def test_a_segment_whose_vad_was_restarted_is_nothing_and_the_next_is_analysed_whole():
    analyser, emitted = analyser_and_results()
    forward(analyser, "vad-old", 1.0, 1.8, ends=False)  # killed: its end never comes
    forward(analyser, "vad-new", 3.0, 4.0, ends=True)
    (broken, said), (span, found) = emitted
    assert broken == (NS, round(1.8 * NS)) and said["nothing"] == \
        "utterance broken off: its VAD went away mid-utterance (vad-old gave way to vad-new)"
    assert span == (3 * NS, 4 * NS) and abs(found["duration"]["value"] - 1.0) < 0.02, found


def test_a_segment_that_lost_messages_is_nothing():
    analyser, emitted = analyser_and_results()
    forward(analyser, "vad", 1.0, 2.0, ends=True, skip=range(10, 13))
    # the chunk after the loss closes the broken segment; the rest, its end mark with it, is too short a segment
    assert emitted[0][1]["nothing"] == "utterance broken off: 3 messages of its audio were lost"
    assert emitted[0][0] == (NS, round(1.0 * NS) + 9 * CHUNK * NS // RATE)

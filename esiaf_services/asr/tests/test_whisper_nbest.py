"""Whisper's n-best (real tiny.en model) and the closed-set choice over it."""
from __future__ import annotations

import numpy as np
import pytest
import soundfile

from esiaf import Audio, AudioFormat
from esiaf.tools.testing import shared_data
from esiaf_services.asr.matching import Match, chosen_first, normalise

CLIP = "speech/cmu_arctic/arctic_a0010.wav"  # "I'm playing a single hand in what looks like a losing game."
NS = 1_000_000_000


@pytest.fixture(scope="module")
def clip() -> np.ndarray:
    """The clip as the service decodes it: int16 over 32768."""
    return soundfile.read(shared_data(CLIP), dtype="int16")[0].astype(np.float32) / 32768


@pytest.fixture(scope="module")
def recognisers():
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf_services.asr.whisper import WhisperRecognizer
    return WhisperRecognizer(n_best=1), WhisperRecognizer(n_best=5)


def test_n_best_gives_distinct_hypotheses_the_first_with_words_the_rest_by_score(recognisers, clip):
    hypotheses = recognisers[1].recognise(clip).hypotheses
    assert len(hypotheses) == 5
    assert len({tuple(normalise(h.text)) for h in hypotheses}) == 5
    assert hypotheses[0].words and not any(h.words for h in hypotheses[1:])
    assert all(0 < h.probability <= 1 for h in hypotheses)
    rest = [h.probability for h in hypotheses[1:]]
    assert rest == sorted(rest, reverse=True)
    assert all("losing game" in h.text for h in hypotheses), [h.text for h in hypotheses]


def test_n_best_1_is_the_single_decode_and_the_n_best_starts_with_it(recognisers, clip):
    one, five = (r.recognise(clip).hypotheses for r in recognisers)
    assert len(one) == 1 and one[0] == five[0]


def segment(samples: np.ndarray) -> Audio:
    """``samples`` (int16 / 32768 at 16 kHz) as one closed VAD segment."""
    pcm = np.round(samples * 32768).astype("<i2").tobytes()
    end_ns = samples.size * NS // 16000
    audio = Audio(topic="vad/speech", stream_id="s", publisher="vad", sequence=1, start_ns=0, end_ns=end_ns,
                  format=AudioFormat(16000, "int16", channels=1), payload=pcm)
    audio.meta.segmentation_ended = True
    audio.meta.segment.start_ns, audio.meta.segment.end_ns = 0, end_ns
    return audio


@pytest.mark.parametrize("n_best", [1, 5])
def test_the_closed_set_choice_finds_a_sentence_only_a_lower_hypothesis_matches(recognisers, clip, tmp_path,
                                                                                  n_best):
    """With exact matching (thresholds 1.0), a set holding the 2nd hypothesis's words but not the
    1st's: n_best 5 reports the 2nd's sentence first, n_best 1 is out of set as before."""
    from esiaf_services.asr.service import Asr, AsrSettings
    first, second = recognisers[1].recognise(clip).hypotheses[:2]
    (tmp_path / "set.txt").write_text(f"{second.text}\ngo forward ten meters\n")
    asr = Asr(AsrSettings(backend="whisper", n_best=n_best, sentences=str(tmp_path / "set.txt"),
                          match_threshold=1.0, char_threshold=1.0,
                          whisper={"prompt_vocabulary": False, "scoring": "text"}))
    asr.setup()
    emitted: list = []
    asr.emit = lambda kind, span, stream_id=None, **payload: None if kind == "partial" else emitted.append(payload)  # type: ignore[method-assign]
    audio = segment(clip)
    asr.on_audio(audio)
    asr.on_segment_end(audio)
    reported = emitted[0]["speech"]["hypotheses"]
    assert len(reported) == n_best
    if n_best == 1:
        assert reported[0].out_of_set and reported[0].text == "" and reported[0].raw_text == first.text
        return
    assert not reported[0].out_of_set and reported[0].text == second.text.strip()
    assert reported[0].raw_text == second.text and reported[0].match_score == 1.0
    assert reported[1].raw_text == first.text and reported[1].out_of_set and reported[1].text == ""
    assert reported[1].words  # the first decode keeps its word times where it is reported


def match(score: float, in_set: bool) -> Match:
    return Match("s", score, in_set)


@pytest.mark.parametrize("matches, order", [
    ([match(0.5, False), match(0.8, True), match(0.9, True)], [2, 0, 1]),  # the best in-set score first
    ([match(0.9, True), match(0.9, True)], [0, 1]),  # a tie goes to the higher ranked
    ([match(0.3, False), match(0.9, True), match(0.9, True)], [1, 0, 2]),
    ([match(0.69, False), match(0.65, True)], [1, 0]),  # an out-of-set score never wins, however high
    ([match(0.5, False), match(0.4, False)], [0, 1]),  # none in the set: as decoded, the first out of set
])
def test_chosen_first(matches, order):
    assert chosen_first(matches) == order

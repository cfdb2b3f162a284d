"""Whisper's decode of one segment: no words past its end (fake and real tiny.en segments), and
the n-best's second beam search from the first decode's encoder output."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import soundfile

from esiaf.tools.testing import shared_data
from esiaf_services.asr.matching import normalise


def fake_segment(text: str, *timed: tuple[str, float, float]) -> SimpleNamespace:
    words = [SimpleNamespace(word=w, start=start, end=end, probability=0.9) for w, start, end in timed]
    return SimpleNamespace(text=text, words=words, no_speech_prob=0.01, avg_logprob=-0.2)


def test_words_timed_past_the_segments_end_are_dropped_from_words_and_text():
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf_services.asr.whisper import within_segment
    segments = [fake_segment(" Where is the hotel located?", (" Where", 0.0, 0.3), (" is", 0.3, 0.5),
                             (" the", 0.5, 0.6), (" hotel", 0.6, 1.0), (" located?", 1.0, 1.9)),
                fake_segment(" Thank you.", (" Thank", 1.98, 1.98), (" you.", 1.98, 1.98))]
    text, words = within_segment(segments, 2.0)
    assert text == "Where is the hotel located?"
    assert [w.word for w in words] == ["Where", "is", "the", "hotel", "located?"]
    text, words = within_segment(segments[:1], 2.0)  # nothing past the end: faster-whisper's own text
    assert text == "Where is the hotel located?" and len(words) == 5 and words[-1].end_s == 1.9


@pytest.fixture(scope="module")
def whisper():
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf_services.asr.whisper import WhisperRecognizer
    return WhisperRecognizer(n_best=10)  # the service's default


def test_a_speaker_cut_off_is_not_given_the_words_whisper_guessed_after_the_cut(whisper):
    """"Lord, but I'm glad to see you again, Phil." cut after "glad to": tiny.en finishes the
    sentence ("... glad to see you.") with words squeezed into the last 20 ms."""
    clip = soundfile.read(shared_data("speech/cmu_arctic/cmu_arctic_us_axb_a0004.wav"), dtype="float32")[0]
    cut = clip[:int(1.68 * 16000)]
    hypotheses = whisper.recognise(cut).hypotheses
    best = hypotheses[0]
    assert best.text.rstrip(".,").endswith("glad to") and best.words[-1].word == "to", best
    assert all(w.start_s < 1.68 - 0.04 for w in best.words)
    assert len({tuple(normalise(h.text)) for h in hypotheses}) == len(hypotheses)  # the n-best stays distinct


def test_the_n_best_reuses_the_first_decodes_encoding_and_finds_the_same_hypotheses(whisper, monkeypatch):
    """The audio is encoded once per segment with n_best 10 (twice before), and the n-best is the
    one that encoding the segment again for the second beam search gives (as it was done before)."""
    clip = soundfile.read(shared_data("speech/cmu_arctic/arctic_a0010.wav"), dtype="float32")[0]
    encode, calls = whisper.model.encode, []
    monkeypatch.setattr(whisper.model, "encode", lambda features: calls.append(features.shape) or encode(features))
    hypotheses = whisper.recognise(clip).hypotheses
    assert len(calls) == 1 and len(hypotheses) >= 5
    assert whisper.alternatives(clip, None, None, (hypotheses[0].text,)) == hypotheses[1:]
    assert len(calls) == 2  # encoded again for the comparison

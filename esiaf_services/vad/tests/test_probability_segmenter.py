"""The probability segmenter (Silero's backend) on chunk sequences with known answers."""
import pytest

from esiaf.speech.segmenter import ProbabilityParams, ProbabilitySegmenter

CHUNK_NS = 20_000_000  # 20 ms
MS = 1_000_000


def feed(segmenter, probabilities, force_end_last=False):
    """Feeds chunks 0..n-1; returns (forwarded chunk indices, [(last chunk, segment, mean probability)])."""
    forwarded, ended = [], []
    for i, p in enumerate(probabilities):
        last = force_end_last and i == len(probabilities) - 1
        for f in segmenter.process(i, i * CHUNK_NS, (i + 1) * CHUNK_NS, p, force_end=last):
            forwarded.append(f.item)
            if f.ended:
                ended.append((f.item, f.segment, f.probability))
    return forwarded, ended


def params(**overrides):
    values = dict(threshold=0.5, threshold_off=0.35, min_speech_ms=100, min_silence_ms=100, max_ms=2000,
                  pre_roll_ms=40, cut_search_ms=400, onset_pad_ms=20)
    return ProbabilityParams(**{**values, **overrides})


def test_segment_with_pre_roll_hysteresis_and_hangover():
    # 0-4 silent, 5-14 speech (0.4 in 10-11 is kept by hysteresis), then silence
    probabilities = [0.1] * 5 + [0.9] * 5 + [0.4, 0.4] + [0.8] * 3 + [0.1] * 10
    forwarded, ended = feed(ProbabilitySegmenter(params()), probabilities)
    assert forwarded == list(range(3, 20))  # 2 chunks of pre-roll, up to the 5th quiet chunk
    # the span starts onset_pad_ms (one chunk) before the first speech-like chunk
    assert ended == [(19, (4 * CHUNK_NS, 15 * CHUNK_NS), pytest.approx((0.9 * 5 + 0.8 + 0.8 * 3) / 10))]


def test_a_burst_shorter_than_min_speech_is_not_a_segment():
    forwarded, ended = feed(ProbabilitySegmenter(params()), [0.1] * 3 + [0.9] * 4 + [0.1] * 20)
    assert forwarded == [] and ended == []


def test_noise_below_threshold_never_opens_and_hysteresis_never_starts_one():
    forwarded, ended = feed(ProbabilitySegmenter(params()), [0.45] * 200)
    assert forwarded == [] and ended == []


def test_a_long_segment_is_cut_at_its_least_speech_like_chunk_and_goes_on():
    # 3 s of speech with one dip (0.36, still speech) at chunk 85: max 2 s, searched over the last 400 ms
    probabilities = [0.9] * 150
    probabilities[85] = 0.36
    forwarded, ended = feed(ProbabilitySegmenter(params()), probabilities + [0.1] * 10)
    assert forwarded == list(range(155))  # nothing lost, nothing twice; ends 100 ms after the speech
    assert [e[0] for e in ended] == [85, 154]
    first, second = ended[0][1], ended[1][1]
    assert first == (0, 86 * CHUNK_NS)
    assert second[0] == 86 * CHUNK_NS and second[1] == 150 * CHUNK_NS


def test_force_end_closes_an_open_segment():
    forwarded, ended = feed(ProbabilitySegmenter(params()), [0.9] * 20, force_end_last=True)
    assert forwarded == list(range(20)) and ended[0][:2] == (19, (0, 20 * CHUNK_NS))


def test_bad_params_are_refused():
    with pytest.raises(ValueError, match="threshold_off"):
        params(threshold_off=0.6)
    with pytest.raises(ValueError, match="cut_search_ms"):
        params(cut_search_ms=3000)
    with pytest.raises(ValueError, match="threshold must be"):
        params(threshold=0)

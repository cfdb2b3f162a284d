"""The double-threshold segmenter on chunk sequences with known answers."""
import math

import pytest

from esiaf.speech.segmenter import Segmenter, SegmenterParams, level_db

CHUNK_NS = 20_000_000  # 20 ms
LOUD, QUIET_KEEP, SILENT = 70.0, 62.0, 40.0


def feed(segmenter, levels, force_end_last=False):
    """Feeds chunks 0..n-1 with the given levels; returns (forwarded chunk indices, ended events)."""
    forwarded, ended = [], []
    for i, level in enumerate(levels):
        last = force_end_last and i == len(levels) - 1
        for f in segmenter.process(i, i * CHUNK_NS, (i + 1) * CHUNK_NS, level, force_end=last):
            forwarded.append(f.item)
            if f.ended:
                ended.append((f.item, f.segment))
    return forwarded, ended


def test_level_is_96_db_at_full_scale_and_minus_inf_for_silence():
    assert level_db(1.0) == 96.0
    assert level_db(0.5) == pytest.approx(96 - 6.0206, abs=1e-3)
    assert level_db(0.0) == -math.inf


def test_segment_with_pre_roll_and_hangover():
    params = SegmenterParams(pre_roll_ms=60, keep_alive_ms=100)
    levels = [SILENT] * 10 + [LOUD] * 5 + [SILENT] * 10
    forwarded, ended = feed(Segmenter(params), levels)
    # 3 chunks of pre-roll (60 ms), 5 speech chunks, then hangover until 100 ms after the last loud chunk
    assert forwarded == list(range(7, 20))
    assert ended == [(19, (10 * CHUNK_NS, 15 * CHUNK_NS))]


def test_keep_alive_level_holds_the_segment_open_but_does_not_start_one():
    params = SegmenterParams(pre_roll_ms=0, keep_alive_ms=100)
    levels = [QUIET_KEEP] * 5 + [LOUD] * 2 + [QUIET_KEEP] * 8 + [SILENT] * 6
    forwarded, ended = feed(Segmenter(params), levels)
    assert forwarded[0] == 5
    assert ended == [(19, (5 * CHUNK_NS, 15 * CHUNK_NS))]


def test_max_length_cuts_and_a_new_segment_starts():
    params = SegmenterParams(pre_roll_ms=0, max_ms=200, keep_alive_ms=100)
    forwarded, ended = feed(Segmenter(params), [LOUD] * 25)
    assert [e[0] for e in ended] == [9, 19]
    assert forwarded == list(range(25))


def test_force_end_closes_an_open_segment_on_that_chunk():
    segmenter = Segmenter(SegmenterParams(pre_roll_ms=0))
    _forwarded, ended = feed(segmenter, [SILENT, LOUD, LOUD, LOUD], force_end_last=True)
    assert ended == [(3, (1 * CHUNK_NS, 4 * CHUNK_NS))]
    assert not segmenter.active


def test_silence_forwards_nothing():
    forwarded, ended = feed(Segmenter(), [SILENT] * 100)
    assert forwarded == [] and ended == []


def test_timing_follows_capture_time_not_chunk_count():
    """Chunk sizes vary: the hangover is measured in nanoseconds of audio."""
    segmenter = Segmenter(SegmenterParams(pre_roll_ms=0, keep_alive_ms=400))
    assert segmenter.process("a", 0, 100_000_000, LOUD)
    assert not segmenter.process("b", 100_000_000, 450_000_000, SILENT)[0].ended  # 350 ms quiet
    out = segmenter.process("c", 450_000_000, 500_000_000, SILENT)  # 400 ms quiet
    assert out[0].ended and out[0].segment == (0, 100_000_000)


def test_bad_thresholds_are_refused():
    with pytest.raises(ValueError, match="db_keep_alive"):
        SegmenterParams(db_min=60, db_keep_alive=65)

"""The ssl component's framing: every sample covered once, "nothing" where there is no source,
forwarded chunks carrying the directions (a real Ssl component, its sends captured; no sockets)."""
from __future__ import annotations

import itertools

import numpy as np

from esiaf.arrays import load_array
from esiaf_services.ssl.offline import localise
from esiaf_services.ssl.tests.test_arrays_doa_tracker import RATE, plane_wave
from esiaf_services.ssl.tracker import angle_difference_deg


def test_frames_cover_the_stream_and_silence_is_covered_with_nothing():
    array = load_array("respeaker4")
    quiet = np.random.default_rng(0).standard_normal((RATE, 4)) * 1e-4  # 1 s at about -80 dB: background
    burst = plane_wave(array, 135.0, seconds=1.0)  # 1 s of a source at 135°
    signals = np.concatenate([quiet, burst, quiet[:5000]])
    forwarded = []
    frames = localise(signals, RATE, chunk_ms=20, array="respeaker4",
                      on_forward=lambda topic, audio, **meta: forwarded.append((topic, audio, meta)))

    duration_s = len(signals) / RATE
    assert frames[0].start_s == 0 and abs(frames[-1].end_s - duration_s) < 1e-6
    assert all(abs(a.end_s - b.start_s) < 1e-6 for a, b in itertools.pairwise(frames)), "frames overlap or leave gaps"
    assert all(abs((f.end_s - f.start_s) - 0.128) < 1e-6 for f in frames[:-1])
    in_quiet = [f for f in frames if f.end_s <= 1.0]
    in_burst = [f for f in frames if f.start_s >= 1.0 + 0.128 and f.end_s <= 2.0]
    assert in_quiet and all(f.azimuth_deg is None for f in in_quiet)
    assert in_burst and all(angle_difference_deg(f.azimuth_deg, 135.0) <= 5 for f in in_burst), in_burst
    assert {f.source_id for f in in_burst} == {"s1"}

    # every chunk forwarded once, in order, unchanged, after its samples were localised
    chunks = [audio for _, audio, _ in forwarded]
    assert [c.sequence for c in chunks] == list(range(1, len(chunks) + 1))
    assert np.array_equal(np.concatenate([c.samples for c in chunks]),
                          np.round(np.clip(signals, -1, 1 - 1 / 32768) * 32768).astype(np.int16))
    assert {topic for topic, _, _ in forwarded} == {"ssl/audio"}
    burst_meta = [meta["ssl_directions"] for _, c, meta in forwarded if 1.2 <= c.start_ns / 1e9 < 1.9]
    assert burst_meta and all(d and d[0].source_id == "s1" and not d[0].elevation_known for d in burst_meta)
    assert all(not meta["ssl_directions"] for _, c, meta in forwarded if c.end_ns / 1e9 <= 1.0)


def test_without_background_selection_every_loud_frame_gets_a_direction_or_a_reason():
    array = load_array("pepper4")
    signals = plane_wave(array, 300.0, seconds=0.6)
    frames = localise(signals, RATE, array="pepper4", bin_snr_db=0, min_confidence=0.999)
    assert frames and all(f.azimuth_deg is None for f in frames)  # no frame is that sure
    frames = localise(signals, RATE, array="pepper4", bin_snr_db=0, algorithm="SRP")
    assert all(angle_difference_deg(f.azimuth_deg, 300.0) <= 5 for f in frames[:-1]), frames


def test_only_the_microphone_channels_are_localised():
    array = load_array("respeaker4")
    mics = plane_wave(array, 250.0, seconds=0.5)
    decoy = plane_wave(array, 30.0, seconds=0.5, seed=7)[:, :1] * 3  # a loud extra channel
    six = np.concatenate([decoy, mics, np.zeros((len(mics), 1))], axis=1)  # ReSpeaker 6-channel firmware layout
    frames = localise(six, RATE, array="respeaker4", channels=6, mic_channels=[1, 2, 3, 4], bin_snr_db=0)
    assert frames and all(angle_difference_deg(f.azimuth_deg, 250.0) <= 5 for f in frames), frames


def test_the_robots_own_loudspeaker_is_self_and_background_and_a_talker_elsewhere_is_not():
    array = load_array("respeaker4")
    forwarded = []
    signals = np.concatenate([plane_wave(array, 100.0, seconds=0.6), plane_wave(array, 200.0, seconds=0.6, seed=3)])
    localise(signals, RATE, array="respeaker4", bin_snr_db=0, self_azimuth_deg=90.0, self_width_deg=40.0,
             on_forward=lambda topic, audio, **meta: forwarded.append((audio, meta["ssl_directions"])))
    loudspeaker = [d for audio, ds in forwarded if 0.2 <= audio.start_ns / 1e9 < 0.5 for d in ds]
    person = [d for audio, ds in forwarded if 0.9 <= audio.start_ns / 1e9 < 1.1 for d in ds]
    assert loudspeaker and all(d.source_id == "self" and d.background for d in loudspeaker)
    assert person and all(d.source_id != "self" and not d.background for d in person)

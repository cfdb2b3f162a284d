"""Arrays, the localiser on plane waves with known directions, and tracking (no sockets)."""
from __future__ import annotations

import numpy as np
import pytest

from esiaf import SetupError
from esiaf.arrays import ArrayError, load_array
from esiaf_services.ssl.doa import ALGORITHMS, SPEED_OF_SOUND_M_S, Localiser, LocaliserError
from esiaf_services.ssl.service import Ssl, SslSettings
from esiaf_services.ssl.tracker import Tracker, angle_difference_deg

RATE = 16000


def plane_wave(array, azimuth_deg, elevation_deg=0.0, seconds=0.128, seed=1) -> np.ndarray:
    """White noise arriving from a far source: each mic gets it delayed by its projection (exact, by FFT)."""
    n = int(RATE * seconds)
    source = np.random.default_rng(seed).standard_normal(n) * 0.1
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    delays_s = -(toward @ array.positions_m) / SPEED_OF_SOUND_M_S  # nearer the source = earlier
    freqs = np.fft.rfftfreq(n, 1 / RATE)
    spectrum = np.fft.rfft(source)
    return np.stack([np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * d), n) for d in delays_s], axis=1)


def test_presets_circular_and_yaml(tmp_path):
    pepper, respeaker = load_array("pepper4"), load_array("respeaker4")
    assert pepper.mics == respeaker.mics == 4
    assert pepper.positions_m[:, 0] == pytest.approx([-0.0267, 0.0343, 0.0])
    assert respeaker.aperture_m == pytest.approx(0.064)
    ring = load_array("circular:6:0.05")
    assert ring.mics == 6 and np.allclose(np.linalg.norm(ring.positions_m, axis=0), 0.05)
    assert not ring.can_tell_elevation
    spec = tmp_path / "tetra.yaml"
    spec.write_text("name: tetra\npositions: [[0.03, 0, 0], [-0.03, 0, 0], [0, 0.03, 0], [0, 0, 0.03]]\n")
    tetra = load_array(str(spec))
    assert tetra.name == "tetra" and tetra.mics == 4 and tetra.can_tell_elevation


@pytest.mark.parametrize("spec, message", [
    ("nonsense", "unknown array 'nonsense'"),
    ("circular:1:0.05", "at least 2 microphones"),
    ("circular:4:-1", "positive radius"),
    ("circular:4", "circular:MICS:RADIUS_M"),
    ("missing.yaml", "cannot read config file missing.yaml"),
])
def test_bad_array_specs_say_what_is_wrong(spec, message):
    with pytest.raises(ArrayError, match=message):
        load_array(spec)


def test_yaml_positions_are_checked(tmp_path):
    for text, message in [("positions: [[0, 0], [0, 0]]", "share a position"),
                          ("positions: [[0, 0, 0, 0], [1, 1]]", r"\[x, y\] or \[x, y, z\]"),
                          ("mics: 4", "positions"),
                          ("positions: [[0, 0], [0.1, 0]]\nradius: 3", "unknown keys radius")]:
        path = tmp_path / "a.yaml"
        path.write_text(text)
        with pytest.raises(ArrayError, match=message):
            load_array(str(path))


def test_a_channel_count_that_does_not_fit_the_array_is_a_setup_error():
    with pytest.raises(SetupError, match="respeaker4 has 4 microphones but the audio has 6 channel"):
        Ssl(SslSettings(array="respeaker4", channels=6))


@pytest.mark.parametrize("algorithm", [a for a in ALGORITHMS if a != "FRIDA"])
@pytest.mark.parametrize("azimuth", [0.0, 67.0, 200.0])
def test_every_algorithm_finds_a_plane_wave(algorithm, azimuth):
    array = load_array("circular:6:0.05")
    localiser = Localiser(array, RATE, algorithm=algorithm, freq_range_hz=(300, 3500))
    found = localiser.locate(plane_wave(array, azimuth))
    assert len(found) == 1 and angle_difference_deg(found[0].azimuth_deg, azimuth) <= 5, found
    assert 0 <= found[0].confidence <= 1


def test_elevation_is_found_where_the_array_can_tell(tmp_path):
    spec = tmp_path / "tetra.yaml"
    spec.write_text("positions: [[0.04, 0, 0], [-0.02, 0.035, 0], [-0.02, -0.035, 0], [0, 0, 0.05]]\n")
    array = load_array(str(spec))
    localiser = Localiser(array, RATE, freq_range_hz=(300, 5000))
    assert localiser.reports_elevation
    found = localiser.locate(plane_wave(array, 120.0, elevation_deg=40.0, seconds=0.256))[0]
    assert angle_difference_deg(found.azimuth_deg, 120.0) <= 6 and abs(found.elevation_deg - 40.0) <= 8, found
    planar = Localiser(load_array("respeaker4"), RATE)
    assert not planar.reports_elevation


@pytest.mark.parametrize("spec", ["circular:2:0.05", "collinear.yaml"])
def test_frida_is_refused_where_it_is_singular(spec, tmp_path):
    if spec.endswith(".yaml"):
        spec = str(tmp_path / spec)
        (tmp_path / "collinear.yaml").write_text("positions: [[0, 0], [0.03, 0], [0.06, 0], [0.09, 0]]\n")
    with pytest.raises(LocaliserError, match=r"FRIDA cannot localise .* singular; choose another algorithm"):
        Localiser(load_array(spec), RATE, algorithm="FRIDA")


def test_frida_is_accepted_on_a_square_array():
    assert Localiser(load_array("respeaker4"), RATE, algorithm="frida").algorithm == "FRIDA"


@pytest.mark.parametrize("kwargs, message", [
    ({"algorithm": "ESPRIT"}, "unknown DOA algorithm 'ESPRIT'"),
    ({"nfft": 300}, "power of two"),
    ({"freq_range_hz": (3000, 1000)}, "increasing"),
    ({"freq_range_hz": (300, 9000)}, "half the sample rate"),
    ({"max_sources": 4}, "fewer than the 4 microphones"),
])
def test_bad_localiser_settings(kwargs, message):
    with pytest.raises(LocaliserError, match=message):
        Localiser(load_array("respeaker4"), RATE, **kwargs)


def test_tracks_keep_their_ids_within_the_gate_and_end_after_the_hold_time():
    tracker = Tracker(gate_deg=20, hold_ms=500)
    ms = 1_000_000
    first = tracker.update(0, [10.0, 200.0])
    assert [t.source_id for t in first] == ["s1", "s2"]
    assert [t.source_id for t in tracker.update(100 * ms, [355.0, 190.0])] == ["s1", "s2"]  # across 0°
    assert [t.source_id for t in tracker.update(200 * ms, [90.0])] == ["s3"]  # outside every gate: new source
    assert [t.source_id for t in tracker.update(550 * ms, [195.0])] == ["s2"]  # s2 was seen 450 ms ago
    assert [t.source_id for t in tracker.update(1200 * ms, [5.0])] == ["s4"]  # s1 ended: ids are never reused
    assert {t.source_id for t in tracker.tracks} == {"s4"}


def test_a_track_follows_its_source_smoothly():
    tracker = Tracker(gate_deg=30, hold_ms=1000, smoothing=0.5)
    for step, azimuth in enumerate([350.0, 0.0, 10.0, 20.0]):
        track, = tracker.update(step, [azimuth])
    assert track.source_id == "s1" and angle_difference_deg(track.azimuth_deg, 11.25) < 0.5


def test_the_microphones_may_be_some_of_the_channels():
    respeaker = load_array("respeaker4")
    assert respeaker.select_channels(4, []) == [0, 1, 2, 3]
    assert respeaker.select_channels(6, [1, 2, 3, 4]) == [1, 2, 3, 4]
    assert respeaker.select_channels(0, [4, 3, 2, 1]) == [4, 3, 2, 1]
    for channels, mics, message in [(6, [], "has 4 microphones but the audio has 6"),
                                    (6, [1, 2, 3], "name 4 distinct channels"),
                                    (6, [1, 1, 2, 3], "name 4 distinct channels"),
                                    (5, [1, 2, 3, 5], r"channels \[5\] do not exist in audio of 5 channel")]:
        with pytest.raises(ArrayError, match=message):
            respeaker.select_channels(channels, mics)
    ssl = Ssl(SslSettings(array="respeaker4", channels=6, mic_channels=[1, 2, 3, 4]))
    assert ssl.format.channels == 6 and ssl.mic_channels == [1, 2, 3, 4]
    with pytest.raises(SetupError, match="do not exist in audio of 4 channel"):
        Ssl(SslSettings(array="respeaker4", channels=4, mic_channels=[1, 2, 3, 4]))


def test_a_track_in_one_place_for_background_s_is_background_and_its_place_is_remembered():
    from esiaf_services.ssl.tracker import Tracker
    tracker = Tracker(gate_deg=12, hold_ms=1000, background_s=8, background_memory_s=60)
    second = 1_000_000_000
    for step in range(100):  # a loudspeaker at 60°, every 100 ms for 10 s; a talker at 200° for 2 s of it
        now = step * second // 10
        tracks = tracker.update(now, [60.0] + ([200.0] if 30 <= step < 50 else []))
        assert tracks[0].background == (now >= 8 * second)
        if len(tracks) > 1:
            assert not tracks[1].background
    near = tracker.update(10 * second, [60.0, 69.0])  # someone speaks 9° from the loudspeaker: within the gate
    assert near[0].background and not near[1].background and near[1].source_id != near[0].source_id
    tracker.expire(20 * second)  # all ended; the loudspeaker's place is remembered
    assert tracker.tracks == []
    again = tracker.update(21 * second, [62.0, 200.0, 72.0])
    assert again[0].background and not again[1].background and not again[2].background
    assert again[0].source_id not in ("s1", "s2")  # a new track, background from its first frame

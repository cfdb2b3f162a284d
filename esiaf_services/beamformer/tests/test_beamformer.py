"""Beamformer: perfect pass-through, SNR gain toward a talker with babble 60° away, steering
without clicks, the service's chunking and ends, and bad settings."""
import math

import numpy as np
import pytest

from esiaf import Audio, AudioFormat, SetupError
from esiaf.arrays import load_array
from esiaf.formats import encode
from esiaf.results import ssl_direction
from esiaf.scenes import NoiseSource, Scene, SpeechSource, render_parts
from esiaf.tools.testing import shared_data
from esiaf_services.beamformer.beam import BeamCore
from esiaf_services.beamformer.offline import snr_gain
from esiaf_services.beamformer.service import Beamformer, BeamformerSettings

RATE = 16000
NS = 1_000_000_000


def test_without_a_target_the_reference_microphone_passes_unchanged_and_in_time():
    core = BeamCore(load_array("respeaker4"), RATE, reference_mic=2)
    stream = core.stream()
    x = np.random.default_rng(1).standard_normal((RATE, 4)) * 0.1
    out = np.concatenate([stream.process(x[i:i + 333]) for i in range(0, RATE, 333)] + [stream.flush()])
    assert len(out) == RATE
    assert np.max(np.abs(out - x[:, 2])) < 1e-12


@pytest.fixture(scope="module")
def two_sources():
    """A talker at 30° (two CMU ARCTIC utterances) and a reader 60° away (90°), 5 dB below, RT60 0.4 s."""
    talker = [shared_data(f"speech/cmu_arctic/{name}.wav") for name in ("cmu_arctic_us_aew_a0001",
                                                                          "cmu_arctic_us_axb_a0004")]
    babble = shared_data("speech/pocketsphinx/librivox/sense_and_sensibility_01_austen_64kb-0870.wav")
    scene = Scene(array="respeaker4", rt60_s=0.4,
                  speech=[SpeechSource(clip=str(talker[0]), azimuth_deg=30, onset_s=2.0),
                          SpeechSource(clip=str(talker[1]), azimuth_deg=30, onset_s=7.0)],
                  noise=[NoiseSource(clip=str(babble), azimuth_deg=90, snr_db=5)])
    return render_parts(scene)


def test_mvdr_gains_at_least_6_db_toward_the_talker(two_sources):
    speech, noise, truth = two_sources
    mvdr = snr_gain(speech, noise, truth, method="mvdr")
    das = snr_gain(speech, noise, truth, method="das")
    assert 3 <= mvdr["snr_in_db"] <= 7
    assert mvdr["gain_db"] >= 6, mvdr
    assert mvdr["gain_db"] > das["gain_db"] + 3, (mvdr, das)  # a 6.4 cm array: delay-and-sum gains little


def test_steering_changes_are_cross_faded_without_clicks():
    core = BeamCore(load_array("respeaker4"), RATE, method="das")
    stream = core.stream()
    t = np.arange(2 * RATE) / RATE
    tone = 0.5 * np.sin(2 * np.pi * 440 * t)
    x = np.repeat(tone[:, None], 4, axis=1)  # the same on every microphone: a source from above
    out = []
    for i in range(0, len(t), core.hop):
        stream.steer(None if i < RATE // 2 else (0.0 if i < RATE else 180.0))
        out.append(stream.process(x[i:i + core.hop]))
    out = np.concatenate(out)
    # a click would be a jump far beyond what a 440 Hz tone of amplitude 0.5 moves in one sample
    assert np.max(np.abs(np.diff(out))) < 1.2 * 2 * np.pi * 440 / RATE * 0.5


def chunk(fmt, samples, start, stream="s", directions=(), end=False):
    audio = Audio(topic="ssl/audio", stream_id=stream, publisher="ssl", sequence=1, start_ns=start * NS // RATE,
                  end_ns=(start + len(samples)) * NS // RATE, format=fmt, payload=encode(samples, fmt))
    audio.meta.ssl_directions.extend(directions)
    audio.meta.end_of_stream = end
    return audio


def test_the_service_publishes_every_chunk_with_its_own_times_and_ends_the_stream(caplog):
    beamformer = Beamformer(BeamformerSettings(array="respeaker4"))
    sent = []
    beamformer.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append((start_ns, end_ns, len(pcm), meta))
    fmt = AudioFormat(RATE, "int16", channels=4)
    x = (np.random.default_rng(2).standard_normal((RATE, 4)) * 3000).astype(np.int16)
    talker = ssl_direction(40.0, 0.0, 0.8, source_id="s1")
    loudspeaker = ssl_direction(300.0, 0.0, 0.9, source_id="s2")
    loudspeaker.background = True
    starts = list(range(0, RATE, 320))
    targets = []
    for start in starts:
        beamformer.on_audio(chunk(fmt, x[start:start + 320], start, directions=[talker, loudspeaker],
                                  end=start == starts[-1]))
        targets += [s.beam.target for s in beamformer.streams.values()]
    assert [s[0] for s in sent] == [s * NS // RATE for s in starts] and all(s[2] == 320 for s in sent)
    assert [s[3]["end_of_stream"] for s in sent] == [False] * (len(starts) - 1) + [True]
    assert len(beamformer.streams) == 0  # the stream's state is gone with it
    # it steered at the talker (its track's azimuth), never at the louder loudspeaker marked background
    assert set(targets) == {40.0}


def test_audio_without_ssl_meta_passes_the_reference_microphone_and_says_so_once(caplog):
    beamformer = Beamformer(BeamformerSettings(array="respeaker4", no_meta_warn_s=0.5))
    sent = []
    beamformer.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append(pcm)
    fmt = AudioFormat(RATE, "int16", channels=4)
    x = (np.random.default_rng(3).standard_normal((RATE, 4)) * 3000).astype(np.int16)
    for start in range(0, RATE, 320):
        beamformer.on_audio(chunk(fmt, x[start:start + 320], start, end=start == RATE - 320))
    assert np.array_equal(np.concatenate(sent), x[:, 0])
    assert sum("no SSL meta" in r.message for r in caplog.records) == 1


@pytest.mark.parametrize("settings, message", [
    (dict(array="circular:1:0.05"), "at least 2 microphones"),
    (dict(array="nowhere.yaml"), "bad beamformer settings"),
    (dict(method="gsc"), "unknown beamforming method"),
    (dict(nfft=300), "power of two"),
    (dict(reference_mic=7), "reference_mic"),
])
def test_bad_settings_are_one_clear_error(settings, message):
    with pytest.raises(SetupError, match=message) as error:
        Beamformer(BeamformerSettings(**settings))
    assert "\n" not in str(error.value)


def test_a_direction_with_a_non_finite_azimuth_is_not_steered_at():
    beamformer = Beamformer(BeamformerSettings(array="respeaker4"))
    sent = []
    beamformer.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append(pcm)
    fmt = AudioFormat(RATE, "int16", channels=4)
    x = (np.random.default_rng(4).standard_normal((RATE // 2, 4)) * 3000).astype(np.int16)
    broken = ssl_direction(0.0, 0.0, 0.9, source_id="s9")
    broken.azimuth_deg = broken.track_azimuth_deg = math.nan
    for start in range(0, RATE // 2, 320):
        beamformer.on_audio(chunk(fmt, x[start:start + 320], start, directions=[broken]))
        assert beamformer.streams["s"].beam.target is None
    assert np.array_equal(np.concatenate(sent), x[:len(np.concatenate(sent)), 0])  # the reference microphone

"""Denoiser: the real DeepFilterNet 3 model lowers noise and keeps speech in time, one utterance
after another; the service publishes every chunk with its own times and meta, flushes at each
utterance's end, and ends each stream; bad settings are one line."""
import numpy as np
import pytest
import soundfile

from esiaf import Audio, AudioFormat, SetupError
from esiaf.formats import encode
from esiaf.tools.testing import shared_data
from esiaf_services.denoiser.filter import ChannelFilter
from esiaf_services.denoiser.service import Denoiser, DenoiserSettings

RATE = 16000
NS = 1_000_000_000
LEAD = RATE // 4  # noise alone before the speech


@pytest.fixture(scope="module")
def noisy():
    """An ARCTIC sentence after 0.25 s of noise alone, white noise 5 dB below it: (clean, noise)."""
    speech, rate = soundfile.read(str(shared_data("speech/cmu_arctic/cmu_arctic_us_aew_a0001.wav")), dtype="float32")
    assert rate == RATE
    speech = np.concatenate([np.zeros(LEAD, np.float32), speech])
    noise = np.random.default_rng(3).standard_normal(len(speech)).astype(np.float32)
    noise *= np.sqrt(np.mean(speech**2) / np.mean(noise**2)) / 10 ** (5 / 20)
    return speech, noise


def run(f: ChannelFilter, x: np.ndarray, hop: int = 320) -> np.ndarray:
    return np.concatenate([f.process(x[i:i + hop]) for i in range(0, len(x), hop)] + [f.flush()])


def lag(reference: np.ndarray, y: np.ndarray, most: int = 800) -> int:
    """The shift (samples) at which ``y`` best matches ``reference``."""
    middle = reference[most:-most]
    return max(range(-most, most + 1), key=lambda k: float(np.dot(middle, y[most + k:len(y) - most + k])))


@pytest.mark.parametrize("hop", [160, 320, 333, 1024])
def test_as_many_samples_come_out_as_went_in_and_in_time(noisy, hop):
    speech, noise = noisy
    y = run(ChannelFilter(RATE), speech + noise, hop)
    assert len(y) == len(speech)
    assert lag(speech, y) == 0  # the look-ahead is held back, not shifted


def test_noise_is_lowered_and_speech_kept(noisy):
    speech, noise = noisy
    out = run(ChannelFilter(RATE), speech + noise)
    quiet = slice(400, LEAD - 400)
    assert 10 * np.log10(np.mean(out[quiet] ** 2) / np.mean(noise[quiet] ** 2)) < -15
    assert np.corrcoef(out, speech)[0, 1] > 0.95 > np.corrcoef(speech + noise, speech)[0, 1]


def test_after_a_flush_the_next_utterance_is_as_good_and_in_time(noisy):
    """Flushed at each utterance's end (the vad's), the filter goes on: every utterance comes out whole,
    in time, as clean as from a new filter."""
    speech, noise = noisy
    f = ChannelFilter(RATE)
    for _ in range(3):
        y = run(f, speech + noise)
        assert len(y) == len(speech) and lag(speech, y) == 0
        assert np.corrcoef(y, speech)[0, 1] > 0.95


@pytest.mark.parametrize("dbfs", [-45, -55, -70])
def test_quiet_speech_is_denoised_as_loud_speech_is(noisy, dbfs):
    """The model alone gives back nothing of speech below about -43 dBFS (a far talker, a microphone of low
    gain: 55-100 dB down); the filter lifts it into the model's range and lowers it again: the same
    speech, at its own level, as clean as at a normal level."""
    speech, noise = noisy
    scale = 10 ** (dbfs / 20) / np.sqrt(np.mean(speech**2))
    f = ChannelFilter(RATE)
    for _ in range(2):  # and the next utterance alike
        y = run(f, (speech + noise) * scale)
        assert len(y) == len(speech) and lag(speech, y) == 0
        assert abs(10 * np.log10(np.mean(y**2) / np.mean((speech * scale) ** 2))) < 2
        assert np.corrcoef(y, speech)[0, 1] > 0.95


def chunk(fmt, samples, start, stream="s", segment=None, ended=False, end=False, publisher="vad", sequence=1,
          speech_until_ns=0):
    audio = Audio(topic="vad/speech", stream_id=stream, publisher=publisher, sequence=sequence,
                  start_ns=start * NS // RATE,
                  end_ns=(start + len(samples)) * NS // RATE, format=fmt, payload=encode(samples, fmt))
    if segment is not None:
        audio.meta.segment.start_ns, audio.meta.segment.end_ns = segment
    audio.meta.segmentation_ended = ended
    audio.meta.end_of_stream = end
    audio.meta.speech_until_ns = speech_until_ns
    return audio


@pytest.mark.parametrize("channels", [1, 2])
def test_the_service_publishes_every_chunk_with_its_own_times_and_meta(channels):
    denoiser = Denoiser(DenoiserSettings(channels=channels))
    sent = []
    denoiser.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append((topic, start_ns, end_ns, pcm, meta))
    fmt = AudioFormat(RATE, "int16", channels=channels)
    rng = np.random.default_rng(1)
    for i in range(20):  # two streams interleaved, each its own filters; an utterance ends at chunk 9
        for stream in ("a", "b"):
            samples = (rng.standard_normal((320, channels)) * 3000).astype(np.int16)
            denoiser.on_audio(chunk(fmt, samples, 320 * i, stream, segment=(320 * (i // 10 * 10) * NS // RATE, 0),
                                    ended=i in (9, 19), end=i == 19, speech_until_ns=0 if i in (9, 19) else
                                    320 * min(i, 6 + i // 10 * 10) * NS // RATE))  # the vad's last speech
        if i == 9:  # the utterance's end flushed what the look-ahead held: all of it is out at once
            assert len([s for s in sent if s[4]["stream_id"] == "a"]) == 10
    for stream in ("a", "b"):
        out = [s for s in sent if s[4]["stream_id"] == stream]
        assert [(s[1], s[2]) for s in out] == [(320 * i * NS // RATE, 320 * (i + 1) * NS // RATE) for i in range(20)]
        assert all(s[3].shape == (320, channels) for s in out)
        assert [s[4]["segmentation_ended"] for s in out] == [i in (9, 19) for i in range(20)]
        assert [s[4]["segment"][0] for s in out] == [320 * (i // 10 * 10) * NS // RATE for i in range(20)]
        assert [s[4]["end_of_stream"] for s in out] == [False] * 19 + [True]
        assert [s[4]["speech_until_ns"] for s in out] == [
            0 if i in (9, 19) else 320 * min(i, 6 + i // 10 * 10) * NS // RATE for i in range(20)]
        assert {s[0] for s in out} == {"denoiser/speech"}
    assert not denoiser.streams  # each stream's filters dropped at its end


def test_an_empty_chunk_that_ends_an_utterance_goes_out_after_the_samples_it_follows():
    denoiser = Denoiser(DenoiserSettings())
    sent = []
    denoiser.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append((len(pcm), meta["segmentation_ended"]))
    fmt = AudioFormat(RATE, "int16")
    for i in range(5):
        denoiser.on_audio(chunk(fmt, np.full(320, 1000, np.int16), 320 * i))
    denoiser.on_audio(chunk(fmt, np.zeros(0, np.int16), 1600, ended=True))
    assert sent == [(320, False)] * 5 + [(0, True)]


@pytest.mark.parametrize("second, sequence", [("vad-b", 1), ("vad-a", 9)], ids=["vad_restarted", "audio_lost"])
def test_an_utterance_broken_off_is_flushed_and_the_next_chunk_says_so(second, sequence):
    """The vad went away mid-utterance (another publisher) or messages were lost: what the recogniser
    would see itself without a denoiser in between. The rest goes out, the next chunk is marked."""
    from esiaf.receiving import broken_off
    denoiser = Denoiser(DenoiserSettings())
    sent = []
    denoiser.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append((start_ns, meta["broken_off"]))
    fmt = AudioFormat(RATE, "int16")
    for i in range(5):  # an utterance begun by vad-a, never ended
        denoiser.on_audio(chunk(fmt, np.full(320, 1000, np.int16), 320 * i, publisher="vad-a", sequence=i + 1))
    denoiser.on_audio(chunk(fmt, np.full(320, 1000, np.int16), 3200, publisher=second, sequence=sequence))
    assert [start for start, _ in sent] == [320 * i * NS // RATE for i in range(5)]  # the broken one's rest
    denoiser.on_audio(chunk(fmt, np.zeros(0, np.int16), 3520, ended=True, publisher=second, sequence=sequence + 1))
    assert [b for _, b in sent] == [False] * 5 + [True, False]  # the next utterance's first chunk says so
    marked = chunk(fmt, np.full(320, 1000, np.int16), 3200, publisher="denoiser", sequence=7)
    marked.meta.broken_off = True
    assert "broke off" in broken_off("denoiser", 6, marked)  # an analyser behind it closes with a nothing
    assert broken_off("denoiser", 6, chunk(fmt, np.full(320, 1000, np.int16), 3200, publisher="denoiser",
                                           sequence=7)) == ""


def test_an_utterance_that_ended_is_not_broken_by_the_next_publisher():
    denoiser = Denoiser(DenoiserSettings())
    sent = []
    denoiser.publish = lambda topic, pcm, start_ns, end_ns, **meta: sent.append(meta["broken_off"])
    fmt = AudioFormat(RATE, "int16")
    denoiser.on_audio(chunk(fmt, np.full(320, 1000, np.int16), 0, publisher="vad-a", ended=True))
    denoiser.on_audio(chunk(fmt, np.full(320, 1000, np.int16), 320, publisher="vad-b", ended=True))
    assert sent == [False, False]


@pytest.mark.parametrize("bad", [{"atten_lim_db": 0}, {"atten_lim_db": 101}, {"post_filter_beta": 0.5},
                                 {"post_filter_beta": -1}])
def test_bad_settings_are_one_line_at_start(bad):
    with pytest.raises(SetupError, match="bad denoiser settings"):
        Denoiser(DenoiserSettings(**bad))

"""Silero VAD on real speech in kitchen noise at 5 dB, against the energy VAD on the clean audio."""
import numpy as np
import pytest
import soundfile
from pydantic import ValidationError

from esiaf import SetupError
from esiaf.speech.segmenter import ProbabilityParams, ProbabilitySegmenter, Segmenter, SegmenterParams, level_db
from esiaf.speech.silero import SileroModel
from esiaf.tools.testing import shared_data
from esiaf_services.vad.service import Vad, VadSettings

RATE = 16000
CHUNK = 320  # 20 ms
NS_PER_SAMPLE = 1_000_000_000 // RATE


def utterances_with_pauses():
    """Four real utterances (pocketsphinx's cards) with 1.5 s of digital silence around each."""
    gap = np.zeros(int(1.5 * RATE))
    parts = [gap]
    for name in ("001", "002", "003", "004"):
        clip, rate = soundfile.read(str(shared_data(f"speech/pocketsphinx/cards/{name}.wav")), dtype="float64")
        assert rate == RATE
        parts += [clip, gap]
    return np.concatenate(parts)


def add_noise(speech, snr_db):
    noise, rate = soundfile.read(str(shared_data("noise/speech_commands_bg/doing_the_dishes.wav")), dtype="float64")
    assert rate == RATE
    noise = noise[RATE:RATE + len(speech)]
    active = np.abs(speech) > 0.02 * np.max(np.abs(speech))
    scale = np.sqrt(np.mean(speech[active] ** 2) / np.mean(noise ** 2) * 10 ** (-snr_db / 10))
    return speech + scale * noise


def segments(segmenter, scores):
    found = []
    for i, score in enumerate(scores):
        for forward in segmenter.process(i, i * CHUNK * NS_PER_SAMPLE, (i + 1) * CHUNK * NS_PER_SAMPLE, score,
                                         force_end=i == len(scores) - 1):
            if forward.ended:
                found.append(tuple(t / 1e9 for t in forward.segment))
    return found


def test_silero_in_noise_finds_the_energy_vads_clean_segments_within_200_ms():
    clean = utterances_with_pauses()
    noisy = add_noise(clean, snr_db=5.0)
    chunks = range(0, len(clean) - CHUNK + 1, CHUNK)
    reference = segments(Segmenter(SegmenterParams()), [level_db(np.max(np.abs(clean[i:i + CHUNK]))) for i in chunks])
    silero = SileroModel().stream(RATE)
    found = segments(ProbabilitySegmenter(ProbabilityParams()), [silero.chunk_probability(noisy[i:i + CHUNK])
                                                                 for i in chunks])
    assert len(reference) == 4, reference
    assert len(found) == 4, (found, reference)
    for (start, end), (ref_start, ref_end) in zip(found, reference, strict=True):
        assert abs(start - ref_start) <= 0.2 and abs(end - ref_end) <= 0.2, (found, reference)
    # the energy VAD on the same noisy audio does not find them: the noise keeps it open
    energy = segments(Segmenter(SegmenterParams()), [level_db(np.max(np.abs(noisy[i:i + CHUNK]))) for i in chunks])
    assert len(energy) != 4 or any(abs(a[0] - b[0]) > 0.2 or abs(a[1] - b[1]) > 0.2
                                   for a, b in zip(energy, reference, strict=False))


def test_silero_hears_no_speech_in_kitchen_noise():
    noise, _ = soundfile.read(str(shared_data("noise/speech_commands_bg/doing_the_dishes.wav")), dtype="float64")
    silero = SileroModel().stream(RATE)
    scores = [silero.chunk_probability(noise[i:i + CHUNK]) for i in range(0, 30 * RATE, CHUNK)]
    assert segments(ProbabilitySegmenter(ProbabilityParams()), scores) == []


@pytest.mark.parametrize("content, message", [(None, "does not exist"), (b"not a model", "cannot load")])
def test_a_missing_or_corrupt_model_is_one_clear_error(tmp_path, content, message):
    path = tmp_path / "model.onnx"
    if content is not None:
        path.write_bytes(content)
    vad = Vad(VadSettings(silero={"model_path": str(path)}))
    with pytest.raises(SetupError, match=message) as error:
        vad.setup()
    assert "\n" not in str(error.value) and str(path) in str(error.value)


def test_unknown_backend_and_rate_are_refused():
    with pytest.raises(ValidationError, match="unknown backend 'webrtc'; one of silero, energy"):
        VadSettings(backend="webrtc")
    with pytest.raises(SetupError, match="8000 or 16000"):
        Vad(VadSettings(sample_rate_hz=44100))

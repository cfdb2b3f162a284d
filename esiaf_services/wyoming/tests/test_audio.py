"""A client's audio converted to what the wyoming service publishes, and its fused text read back."""
from __future__ import annotations

import numpy as np
import pytest

from esiaf_services.wyoming.audio import AudioError, ClientAudio, client_format
from esiaf_services.wyoming.commands import PUBLISHED
from esiaf_services.wyoming.server import transcript_text


def dominant_hz(samples: np.ndarray, rate_hz: int) -> float:
    spectrum = np.abs(np.fft.rfft(samples.astype(np.float64).ravel()))
    return float(np.fft.rfftfreq(len(samples), 1 / rate_hz)[np.argmax(spectrum)])


def test_48khz_stereo_32bit_becomes_16khz_mono_16bit_in_chunks():
    rate = 48_000
    t = np.arange(rate) / rate
    tone = 0.5 * np.sin(2 * np.pi * 440 * t)
    stereo = (np.stack([tone, tone], axis=1) * 2**31).astype("<i4")
    audio = ClientAudio(client_format(rate, 4, 2), PUBLISHED)
    chunks = [audio.convert(stereo[i:i + 4800].tobytes()) for i in range(0, rate, 4800)]
    chunks.append(audio.convert(b"", last=True))
    out = np.concatenate(chunks)
    assert out.dtype == np.int16 and out.shape[1] == 1
    assert abs(len(out) - 16_000) <= 1  # one second, nothing held back
    assert abs(dominant_hz(out, 16_000) - 440) < 2
    assert 0.45 < np.abs(out).max() / 32768 < 0.55


@pytest.mark.parametrize(("rate", "width", "channels"), [(4000, 2, 1), (16000, 5, 1), (16000, 2, 0),
                                                         ("16000", 2, 1), (16000, 2, 99)])
def test_formats_out_of_range_are_refused(rate, width, channels):
    with pytest.raises(AudioError):
        client_format(rate, width, channels)


def test_a_chunk_cut_mid_frame_is_refused():
    audio = ClientAudio(client_format(16000, 2, 2), PUBLISHED)
    with pytest.raises(AudioError, match="whole number"):
        audio.convert(b"\x00" * 6)


def fused(start_ns: int, text: str, **hypothesis) -> dict:
    return {"anchor": {"span": {"start_ns": start_ns, "end_ns": start_ns + 1},
                       "speech": {"hypotheses": [{"text": text, **hypothesis}]}}}


def test_the_transcript_is_the_utterances_in_capture_order():
    results = {2: fused(200, "what is a chatbot"), 1: fused(100, "how big is the rcmp"),
               3: fused(300, "", raw_text="open the door", out_of_set=True), 4: fused(400, "")}
    assert transcript_text(results) == "how big is the rcmp what is a chatbot open the door"

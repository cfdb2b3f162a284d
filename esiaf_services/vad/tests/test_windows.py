"""The vad decides per Silero window: the same segments at any transport chunk size, and what it
forwards is the stream's own audio, contiguous, in few messages, ending where segments end."""
import numpy as np
import pytest

from esiaf import Audio, AudioFormat
from esiaf.speech.windows import MAX_MESSAGE_S, Piece
from esiaf_services.vad.service import Vad, VadSettings
from esiaf_services.vad.tests.test_silero import RATE, add_noise, utterances_with_pauses

FORMAT = AudioFormat(RATE, "int16", channels=1)
NS_PER_SAMPLE = 1_000_000_000 // RATE


class Recording(Vad):
    """The vad, with what it publishes and emits kept instead of sent."""

    def __init__(self, settings: VadSettings):
        super().__init__(settings)
        self.sent: list[tuple[bytes, int, int, dict]] = []
        self.spans: list[tuple[int, int]] = []  # of its vad results
        self.starts: list[tuple[int, int, int]] = []  # its speech_start events: span, and when (messages sent)

    def publish(self, topic, audio, start_ns, end_ns, **meta):
        self.sent.append((bytes(audio), start_ns, end_ns, meta))
        return len(self.sent)

    def emit(self, kind, span, **payload):
        if kind == "speech_start":
            self.starts.append((*span, len(self.sent)))
        else:
            self.spans.append(span)


def opening(vad: Recording) -> list:
    """The first message forwarded of each segment."""
    firsts, new = [], True
    for message in vad.sent:
        if new and message[0]:
            firsts.append(message)
            new = False
        new = new or bool(message[3].get("segmentation_ended"))
    return firsts


def play(pcm: bytes, chunk_frames: int, backend: str = "silero") -> Recording:
    vad = Recording(VadSettings(backend=backend))
    vad.setup()
    total = len(pcm) // 2
    for sequence, first in enumerate(range(0, total, chunk_frames), 1):
        last = min(first + chunk_frames, total)
        audio = Audio("grabber/audio", "s", "grabber", sequence, first * NS_PER_SAMPLE, last * NS_PER_SAMPLE,
                      FORMAT, pcm[2 * first:2 * last])
        audio.meta.end_of_stream = last == total
        vad.on_audio(audio)
        if audio.meta.end_of_stream:  # its only input ended: the SDK calls this next
            vad.on_end_of_stream("s", audio)
    return vad


@pytest.fixture(scope="module")
def noisy_pcm() -> bytes:
    noisy = add_noise(utterances_with_pauses(), snr_db=5.0)
    noisy *= 0.9 / np.max(np.abs(noisy))
    return (noisy * 32767).astype("<i2").tobytes()


def test_segments_do_not_depend_on_the_chunk_size(noisy_pcm):
    found = {ms: play(noisy_pcm, RATE * ms // 1000).spans for ms in (10, 20, 50, 100, 128)}
    assert len(found[20]) >= 4, found[20]
    for ms, spans in found.items():
        assert spans == found[20], (ms, spans, found[20])
    # boundaries fall on the model's 32 ms windows (or the span's onset pad before one)
    assert all(end % (512 * NS_PER_SAMPLE) == 0 for _, end in found[20])


@pytest.mark.parametrize("chunk_ms", [20, 50, 100])
def test_what_is_forwarded_is_the_streams_audio_contiguous_with_one_end_per_segment(noisy_pcm, chunk_ms):
    vad = play(noisy_pcm, RATE * chunk_ms // 1000)
    segment_audio = b""
    ended = previous_end_ns = 0
    for payload, start_ns, end_ns, meta in vad.sent:
        first, last = start_ns // NS_PER_SAMPLE, end_ns // NS_PER_SAMPLE
        assert payload == noisy_pcm[2 * first:2 * last]  # the stream's own samples at its capture times
        assert last - first <= MAX_MESSAGE_S * RATE
        if segment_audio:  # within a segment, each message starts where the last one ended
            assert start_ns == previous_end_ns
        segment_audio += payload
        previous_end_ns = end_ns
        if meta.get("segmentation_ended"):
            assert meta["segment"] == vad.spans[ended]
            ended += 1
            segment_audio = b""
    assert ended == len(vad.spans)
    assert vad.sent[-1][3]["end_of_stream"]  # after the last segment: consumers hear that the stream ended
    # each segment was announced before any of its audio was forwarded, its start within the onset padding
    # of the segment's: on a jump from quiet or after speech_start_ms (150 ms) of speech, before the segment
    # opens at min_speech_ms. A jump may announce a burst too short to become a segment too (here one, at
    # 10.3 s: the price of not waiting for speech_start_ms), never a second start within a segment
    pad_ns = int(VadSettings().silero.onset_pad_ms * 1e6)
    starts = [s for s in vad.starts if any(a <= s[0] <= b for a, b in vad.spans)]
    assert len(vad.starts) - len(starts) <= 1, (vad.starts, vad.spans)
    for (start, decided, sent), (segment_start, segment_end), first in zip(starts, vad.spans, opening(vad),
                                                                          strict=True):
        assert segment_start <= start <= segment_start + pad_ns and start < decided <= segment_end
        assert sent <= vad.sent.index(first)

    # no more messages than chunks of the audio forwarded (plus a segment's end mid-chunk): the
    # pre-roll and the onset held back go out together, and at 20 ms a message is a 32 ms window
    chunks = sum(len(payload) for payload, *_ in vad.sent) / (2 * RATE * chunk_ms / 1000)
    assert len(vad.sent) <= (chunks if chunk_ms < 32 else chunks + len(vad.spans) + 1), (len(vad.sent), chunks)


def test_a_stream_ending_inside_a_window_ends_its_segment_with_the_last_samples(noisy_pcm):
    cut = 3 * RATE + 100  # inside the first utterance, inside a window
    vad = play(noisy_pcm[:2 * cut], 320)
    assert len(vad.spans) == 1
    payload, _, end_ns, meta = vad.sent[-1]
    assert meta["segmentation_ended"] and meta["end_of_stream"]
    assert end_ns == cut * NS_PER_SAMPLE and payload.endswith(noisy_pcm[2 * cut - 200:2 * cut])


def test_the_energy_backend_still_decides_per_chunk(noisy_pcm):
    clean = (utterances_with_pauses() * 0.9 * 32767).astype("<i2").tobytes()
    spans = {ms: play(clean, RATE * ms // 1000, "energy").spans for ms in (20, 100)}
    assert len(spans[20]) == 4
    assert all(end % (100 * 1_000_000) == 0 for _, end in spans[100])


def test_a_cut_inside_a_piece_interpolates_its_capture_time():
    piece = Piece(bytes(range(8)), 1_000, 2_000, frame=10, frames=4)
    head, tail = piece.split(1, 2)
    assert (head.payload, head.start_ns, head.end_ns, head.frame, head.frames) == (b"\x00\x01", 1_000, 1_250, 10, 1)
    assert (tail.payload, tail.start_ns, tail.end_ns, tail.frame, tail.frames) == (bytes(range(2, 8)), 1_250, 2_000,
                                                                                   11, 3)

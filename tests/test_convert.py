"""Format conversion: quality, exact round trips, streaming equals one-shot, switches lose nothing."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from esiaf.audio import Audio, SampleClock
from esiaf.convert import StreamConverter, convert, convert_type
from esiaf.formats import AudioFormat, FormatError, decode, encode
from esiaf.links import InputLink, OutputLink
from tests.test_formats import random_samples


def sine(fmt: AudioFormat, seconds: float, hz: float = 1000.0, amplitude: float = 0.5) -> np.ndarray:
    """A sine in ``fmt``'s sample type, (frames, channels)."""
    t = np.arange(round(seconds * fmt.sample_rate_hz)) / fmt.sample_rate_hz
    values = np.repeat((amplitude * np.sin(2 * np.pi * hz * t))[:, None], fmt.channels, axis=1)
    if fmt.sample_type.startswith("float"):
        return values.astype(fmt.sample_type)
    scaled = np.rint(values * fmt.full_scale).astype(np.int64)
    return scaled + (int(fmt.full_scale) if fmt.sample_type.startswith("u") else 0)


def stream(converter: StreamConverter, payload: bytes, chunk_frames, start_ns: int = 0) -> tuple[bytes, list]:
    """Feeds ``payload`` in chunks of the sizes ``chunk_frames`` yields, flushes; output and spans."""
    src = converter.src
    clock = SampleClock(start_ns, src.sample_rate_hz)
    total = src.frames_in(payload)
    out, spans = [], []
    while clock.frames < total:
        frames = min(next(chunk_frames), total - clock.frames)
        first = clock.frames
        start, end = clock.advance(frames)
        chunk = converter.convert(payload[first * src.bytes_per_frame:clock.frames * src.bytes_per_frame],
                                  start, end, last=clock.frames == total)
        out.append(chunk.payload)
        spans.append((chunk.start_ns, chunk.end_ns, len(chunk.payload) // converter.dst.bytes_per_frame))
    return b"".join(out), spans


def snr_db(reference: np.ndarray, signal: np.ndarray) -> float:
    return 10 * np.log10(np.sum(reference ** 2) / np.sum((signal - reference) ** 2))


def test_1khz_sine_48k_to_16k_and_back_keeps_60_db_snr():
    fmt48, fmt16 = AudioFormat(48000, "int16"), AudioFormat(16000, "int16")
    original = encode(sine(fmt48, 2.0), fmt48)
    rng = np.random.default_rng(3)
    sizes = iter(lambda: int(rng.integers(1, 2000)), None)
    down, _ = stream(StreamConverter(fmt48, fmt16), original, sizes)
    back, _ = stream(StreamConverter(fmt16, fmt48), down, sizes)
    assert len(back) == len(original)  # flushed: nothing held back, nothing added
    reference = decode(original, fmt48)[4800:-4800, 0] / 32768
    result = decode(back, fmt48)[4800:-4800, 0] / 32768  # the edges see the zeros around the signal
    assert snr_db(reference, result) >= 60


@pytest.mark.parametrize("narrow, wide", [
    ("int8", "int16"), ("uint8", "int16"), ("int16", "int24"), ("int16", "int32"), ("int24", "int32"),
    ("uint16", "int32"), ("int16", "float32"), ("int24", "float32"), ("int32", "float64"),
    ("uint24", "float64"), ("float32", "float64"), ("int16", "uint16")])
@pytest.mark.parametrize("endianness", ["little", "big"])
def test_integer_and_float_round_trips_are_exact_where_representable(narrow, wide, endianness):
    src = AudioFormat(16000, narrow, "little", 2)
    dst = AudioFormat(16000, wide, endianness, 2)
    samples = random_samples(src, 1000, np.random.default_rng(5))
    payload = encode(samples, src)
    there = convert(payload, src, dst)
    assert convert(there, dst, src) == payload
    streamed, _ = stream(StreamConverter(src, dst), payload, iter(lambda: 77, None))
    assert streamed == there


def test_integers_are_rounded_and_clipped():
    fmt16, fmt32, flt = AudioFormat(16000, "int16"), AudioFormat(16000, "int32"), AudioFormat(16000, "float32")
    assert convert_type(np.array([[65535], [-98304], [2 ** 31 - 1]]), fmt32, fmt16).ravel().tolist() == [
        1, -2, 32767]  # 0.99998 -> 1, -1.5 -> -2 (to even), full scale stays in range
    assert convert_type(np.array([[1.0], [-1.5], [0.5]], dtype=np.float32), flt, fmt16).ravel().tolist() == [
        32767, -32768, 16384]


@pytest.mark.parametrize("src, dst", [
    (AudioFormat(48000, "int32"), AudioFormat(16000, "int16")),
    (AudioFormat(44100, "int16", channels=2), AudioFormat(16000, "int16", channels=2)),
    (AudioFormat(16000, "int16"), AudioFormat(48000, "int24", "big")),
    (AudioFormat(22050, "float32", "big", 4), AudioFormat(16000, "uint8", channels=4)),
])
def test_streaming_over_random_chunk_sizes_equals_one_shot_within_2_lsb(src, dst):
    payload = encode(random_samples(src, src.sample_rate_hz, np.random.default_rng(7)) // 4
                     if not src.sample_type.startswith("float")
                     else random_samples(src, src.sample_rate_hz, np.random.default_rng(7)) / 4, src)
    rng = np.random.default_rng(11)
    streamed, spans = stream(StreamConverter(src, dst), payload, iter(lambda: int(rng.integers(1, 3000)), None),
                             start_ns=1_000_000_000)
    one_shot = convert(payload, src, dst)
    assert len(streamed) == len(one_shot)
    difference = np.abs(decode(streamed, dst).astype(np.int64) - decode(one_shot, dst).astype(np.int64))
    assert difference.max() <= 2
    # stamped from output sample counts: contiguous, and the last chunk ends with the signal
    assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))
    assert spans[0][0] == 1_000_000_000
    assert abs(spans[-1][1] - 2_000_000_000) <= 1_000_000_000 // dst.sample_rate_hz


def test_channel_counts_are_never_converted():
    with pytest.raises(FormatError, match="channel counts are never converted"):
        StreamConverter(AudioFormat(16000, channels=4), AudioFormat(16000, channels=1))


def audio_message(fmt: AudioFormat, payload: bytes, sequence: int, span: tuple[int, int], **meta) -> Audio:
    audio = Audio(topic="t", stream_id="s", publisher="p", sequence=sequence, start_ns=span[0], end_ns=span[1],
                  format=fmt, payload=payload)
    for key, value in meta.items():
        setattr(audio.meta, key, value)
    return audio


def test_a_switch_at_a_message_boundary_loses_and_duplicates_nothing():
    """A producer publishing 48 kHz switches its topic from 16 kHz to 48 kHz and back mid-stream; a
    16 kHz consumer receives every message in order. Nothing is dropped or doubled, the consumer's
    spans are contiguous, sequence numbers too, and the sine survives the switches."""
    fmt48, fmt16 = AudioFormat(48000, "int16"), AudioFormat(16000, "int16")
    signal = encode(sine(fmt48, 1.2, hz=440), fmt48)
    producer, consumer = OutputLink("t", fmt48), InputLink(fmt16)
    clock = SampleClock(0, 48000)
    chunk_bytes = 960 * fmt48.bytes_per_frame  # 20 ms
    sequence, received = 0, []
    for index in range(60):
        producer.assigned = {0: fmt16, 20: fmt48, 40: fmt16}.get(index, producer.assigned)
        payload = signal[index * chunk_bytes:(index + 1) * chunk_bytes]
        last = index == 59
        for out in producer.messages(payload, *clock.advance(960), "s", end_of_stream=last):
            sequence += 1
            meta = {"end_of_stream": last} if out.main else {}
            message = audio_message(out.format, out.chunk.payload, sequence, (out.chunk.start_ns, out.chunk.end_ns),
                                    **meta)
            received += consumer.receive(message)
    assert sequence == 61  # 60 chunks and the resampler tail sent at the switch away from 16 kHz
    assert [a.sequence for a in received] == list(range(1, 62))
    assert all(a.format == fmt16 for a in received)
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(received))
    frames = sum(a.frames for a in received)
    assert frames == 16000 * 1.2 == (received[-1].end_ns - received[0].start_ns) * 16000 // 10 ** 9
    got = np.concatenate([decode(a.payload, fmt16)[:, 0] for a in received]) / 32768
    expected = 0.5 * np.sin(2 * np.pi * 440 * np.arange(len(got)) / 16000)
    error = np.abs(got - expected)
    assert np.median(error) < 1e-3
    # a switch costs a short transient (the flushed resampler saw silence after its last chunk)
    assert np.mean(error > 0.05) < 0.01


def test_two_streams_interleaved_on_one_topic_each_keep_their_own_resampler():
    """A producer publishes two streams on one topic (a grabber with two inputs), chunk by chunk in
    turn, declared 48 kHz and assigned 16 kHz. Each stream comes out as if it were alone: one message
    per chunk (no resampler tail flushed at every change of stream), contiguous spans, every frame,
    and its own sine without the transient a restarted resampler leaves."""
    fmt48, fmt16 = AudioFormat(48000, "int16"), AudioFormat(16000, "int16")
    producer = OutputLink("t", fmt48)
    producer.assigned = fmt16
    tones = {"a": 440, "b": 660}
    signals = {s: encode(sine(fmt48, 1.0, hz=hz), fmt48) for s, hz in tones.items()}
    clocks = {s: SampleClock(start, 48000) for s, start in (("a", 0), ("b", 5_000_000_000))}
    chunk_bytes = 960 * fmt48.bytes_per_frame
    sent: dict[str, list] = {"a": [], "b": []}
    for index in range(50):
        for stream in ("a", "b"):
            last = index == 49
            payload = signals[stream][index * chunk_bytes:(index + 1) * chunk_bytes]
            for out in producer.messages(payload, *clocks[stream].advance(960), stream, end_of_stream=last):
                assert out.stream_id == stream and out.format == fmt16
                sent[stream].append(out)
    for stream, hz in tones.items():
        messages = sent[stream]
        assert len(messages) == 50 and all(m.main for m in messages)
        spans = [(m.chunk.start_ns, m.chunk.end_ns) for m in messages if m.chunk.payload]
        assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))
        got = np.concatenate([decode(m.chunk.payload, fmt16)[:, 0] for m in messages]) / 32768
        assert len(got) == 16000
        expected = 0.5 * np.sin(2 * np.pi * hz * np.arange(len(got)) / 16000)
        assert np.max(np.abs(got - expected)[:-200]) < 0.02  # the very end: the stream's own last flush


def test_a_message_in_the_declared_format_is_handed_on_as_it_came_until_the_format_changes():
    fmt16, fmt48 = AudioFormat(16000, "int16"), AudioFormat(48000, "int16")
    consumer = InputLink(fmt16)
    first = audio_message(fmt16, encode(sine(fmt16, 0.02, hz=440), fmt16), 1, (0, 20_000_000))
    assert consumer.receive(first) == [first] and consumer.receive(first)[0] is first  # nothing to convert
    second = audio_message(fmt48, encode(sine(fmt48, 0.02, hz=440), fmt48), 2, (20_000_000, 40_000_000))
    [converted] = consumer.receive(second)
    assert converted.format == fmt16 and converted.sequence == 2 and converted.start_ns == 20_000_000
    assert converted.frames <= 320  # converted (a resampler holds its first milliseconds back)

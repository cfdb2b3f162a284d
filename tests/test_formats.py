import itertools

import numpy as np
import pytest

from esiaf import formats
from esiaf.audio import SampleClock
from esiaf.formats import SAMPLE_TYPES, AudioFormat, FormatError, decode, encode, peak, to_float
from esiaf.proto import esiaf_pb2 as pb


def random_samples(fmt: AudioFormat, frames: int, rng) -> np.ndarray:
    if fmt.sample_type.startswith("float"):
        return rng.uniform(-1, 1, (frames, fmt.channels)).astype(fmt.sample_type)
    bits = fmt.bytes_per_sample * 8
    lo, hi = (0, 2 ** bits - 1) if fmt.sample_type.startswith("u") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
    return rng.integers(lo, hi, (frames, fmt.channels), endpoint=True)


@pytest.mark.parametrize("sample_type", SAMPLE_TYPES)
@pytest.mark.parametrize("endianness", ["little", "big"])
def test_encode_decode_round_trip_is_exact(sample_type, endianness):
    fmt = AudioFormat(48000, sample_type, endianness, 3)
    samples = random_samples(fmt, 101, np.random.default_rng(1))
    payload = encode(samples, fmt)
    assert len(payload) == 101 * 3 * fmt.bytes_per_sample
    assert np.array_equal(decode(payload, fmt).astype(np.float64), samples.astype(np.float64))


def test_int24_is_packed_three_bytes_little_and_big():
    assert encode(np.array([[-2]]), AudioFormat(16000, "int24", "little")) == b"\xfe\xff\xff"
    assert encode(np.array([[0x123456]]), AudioFormat(16000, "int24", "big")) == b"\x12\x34\x56"
    assert decode(b"\x00\x00\x80", AudioFormat(16000, "int24")).item() == -(2 ** 23)


def test_proto_and_dict_round_trip():
    fmt = AudioFormat(44100, "uint24", "big", 4)
    assert AudioFormat.from_proto(fmt.to_proto()) == fmt
    assert AudioFormat.from_dict(fmt.to_dict()) == fmt


def test_formats_read_from_messages_are_kept_but_bounded_and_bad_ones_always_refused():
    fmt = AudioFormat(22050, "int16", "big", 2)
    first, again = AudioFormat.from_proto(fmt.to_proto()), AudioFormat.from_proto(fmt.to_proto())
    assert first == fmt and again is first  # one instance per format: not made anew per message
    for rate in range(8000, 8000 + 3 * formats.MAX_FORMATS_KEPT):  # a peer forging formats
        assert AudioFormat.from_proto(AudioFormat(rate).to_proto()).sample_rate_hz == rate
    assert len(formats._FROM_PROTO) <= formats.MAX_FORMATS_KEPT
    for _ in range(2):
        with pytest.raises(FormatError, match="unknown sample type 99"):
            AudioFormat.from_proto(pb.AudioFormat(sample_rate_hz=16000, sample_type=99, channels=1))
        with pytest.raises(FormatError, match="sample rate must be positive"):
            AudioFormat.from_proto(pb.AudioFormat(sample_rate_hz=0, sample_type=pb.SAMPLE_TYPE_INT16, channels=1))


def test_float_scaling_and_peak():
    fmt = AudioFormat(16000, "uint8")
    assert to_float(np.array([[0], [128], [255]]), fmt).ravel().tolist() == [-1.0, 0.0, 127 / 128]
    assert peak(np.array([[-32768], [100]]), AudioFormat()) == 1.0


@pytest.mark.parametrize("bad", [dict(sample_type="int12"), dict(endianness="middle"), dict(channels=0),
                                 dict(sample_rate_hz=0)])
def test_bad_formats_are_refused(bad):
    with pytest.raises(FormatError):
        AudioFormat(**bad)


def test_partial_frames_are_refused():
    with pytest.raises(FormatError, match="whole number"):
        decode(b"\0" * 5, AudioFormat(16000, "int16", channels=2))


def test_sample_clock_stamps_from_sample_counts_without_drift():
    clock = SampleClock(origin_ns=1_000, sample_rate_hz=44100)
    spans = [clock.advance(441) for _ in range(1000)]  # 1000 chunks of 10 ms
    assert spans[0] == (1_000, 1_000 + 10_000_000)
    assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))  # contiguous
    assert spans[-1][1] == 1_000 + 10_000_000_000  # exactly 10 s, no rounding drift

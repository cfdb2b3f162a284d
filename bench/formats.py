"""Format conversion cost: CPU per second of audio and per chunk, for the common paths, in one run.

For each path (48 kHz int32 → 16 kHz int16, 16 kHz int16 → 16 kHz float32, 44.1 kHz int16 →
16 kHz int16, 16 kHz int16 → 48 kHz int16) and each chunk size (10, 64, 128 ms) it feeds
``--seconds`` of noise through the SDK's streaming converter (esiaf.convert.StreamConverter: decode,
scale, soxr streaming resampler, encode, sample-count stamps), flushed at the end, and beside it
the same audio through the one-shot conversion (esiaf.convert.convert), which has no per-chunk
cost. The best of ``--repeats`` runs is kept (CPU time of this process). It also reports each
resampler's delay (audio held back until the next chunk or the flush).

    python bench/formats.py [--seconds 30] [--repeats 5]

It prints a table, then ``name=value`` lines: ``<path>_<chunk>ms_us_per_chunk``,
``<path>_<chunk>ms_ms_per_s`` (CPU ms per second of audio), ``<path>_oneshot_ms_per_s``,
``<path>_delay_ms``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from esiaf.audio import SampleClock
from esiaf.convert import StreamConverter, convert
from esiaf.formats import AudioFormat, encode

PATHS = {
    "48k_int32_to_16k_int16": (AudioFormat(48000, "int32"), AudioFormat(16000, "int16")),
    "16k_int16_to_16k_float32": (AudioFormat(16000, "int16"), AudioFormat(16000, "float32")),
    "44k1_int16_to_16k_int16": (AudioFormat(44100, "int16"), AudioFormat(16000, "int16")),
    "16k_int16_to_48k_int16": (AudioFormat(16000, "int16"), AudioFormat(48000, "int16")),
}
CHUNKS_MS = (10, 64, 128)


def noise(fmt: AudioFormat, seconds: float) -> bytes:
    values = np.random.default_rng(1).uniform(-0.5, 0.5, (round(fmt.sample_rate_hz * seconds), fmt.channels))
    if fmt.sample_type.startswith("float"):
        return encode(values.astype(fmt.sample_type), fmt)
    return encode(np.rint(values * fmt.full_scale).astype(np.int64), fmt)


def streamed_cpu_s(src: AudioFormat, dst: AudioFormat, payload: bytes, chunk_ms: int) -> tuple[float, int]:
    """CPU seconds to convert ``payload`` chunk by chunk, and the number of chunks."""
    converter = StreamConverter(src, dst)
    frames = src.sample_rate_hz * chunk_ms // 1000
    step = frames * src.bytes_per_frame
    clock = SampleClock(0, src.sample_rate_hz)
    pieces = [payload[i:i + step] for i in range(0, len(payload), step)]
    spans = [clock.advance(len(p) // src.bytes_per_frame) for p in pieces]
    started = time.process_time()
    for index, (piece, span) in enumerate(zip(pieces, spans, strict=True)):
        converter.convert(piece, *span, last=index == len(pieces) - 1)
    return time.process_time() - started, len(pieces)


def delay_ms(src: AudioFormat, dst: AudioFormat) -> float:
    """Audio the streaming resampler holds back, in ms (after 1 s of 10 ms chunks)."""
    if src.sample_rate_hz == dst.sample_rate_hz:
        return 0.0
    converter = StreamConverter(src, dst)
    payload = noise(src, 1.0)
    step = src.sample_rate_hz // 100 * src.bytes_per_frame
    out_frames = 0
    clock = SampleClock(0, src.sample_rate_hz)
    for i in range(0, len(payload), step):
        out = converter.convert(payload[i:i + step], *clock.advance(step // src.bytes_per_frame))
        out_frames += len(out.payload) // dst.bytes_per_frame
    return 1000.0 - out_frames * 1000 / dst.sample_rate_hz


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="audio per measurement (30)")
    parser.add_argument("--repeats", type=int, default=5, help="runs per measurement; the best is kept (5)")
    args = parser.parse_args()
    figures: dict[str, float] = {}
    print(f"{'path':28} {'chunk':>6} {'µs/chunk':>9} {'CPU ms per s of audio':>22}")
    for name, (src, dst) in PATHS.items():
        payload = noise(src, args.seconds)
        for chunk_ms in CHUNKS_MS:
            cpu_s, chunks = min(streamed_cpu_s(src, dst, payload, chunk_ms) for _ in range(args.repeats))
            figures[f"{name}_{chunk_ms}ms_us_per_chunk"] = cpu_s / chunks * 1e6
            figures[f"{name}_{chunk_ms}ms_ms_per_s"] = cpu_s / args.seconds * 1e3
            print(f"{name:28} {chunk_ms:>4}ms {cpu_s / chunks * 1e6:9.1f} {cpu_s / args.seconds * 1e3:22.3f}")
        oneshot = []
        for _ in range(args.repeats):
            started = time.process_time()
            convert(payload, src, dst)
            oneshot.append(time.process_time() - started)
        figures[f"{name}_oneshot_ms_per_s"] = min(oneshot) / args.seconds * 1e3
        figures[f"{name}_delay_ms"] = delay_ms(src, dst)
        print(f"{name:28} {'whole':>6} {'':9} {min(oneshot) / args.seconds * 1e3:22.3f}   "
              f"(one-shot; streaming delay {figures[f'{name}_delay_ms']:.1f} ms)")
    for key, value in figures.items():
        print(f"{key}={value:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

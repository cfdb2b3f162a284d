"""What many stream names cost a component's memory: the vad's handler fed one chunk of each of N streams.

    python -m bench.streams [--streams 10000] [--max-streams 256]

A stream whose source dies never ends, and a peer may name a new stream in every message; a
component that kept each stream's state until its end grew for as long as it ran (the vad: a
segmenter and a Silero state per stream). The vad service's class, its model loaded, takes one
50 ms chunk of silence from each of ``--streams`` stream names, back to back in this process
(nothing sent), and the bench reports the streams whose state it kept, those it forgot
(``forgotten_streams``) and the growth of this process's resident memory.
"""
from __future__ import annotations

import argparse

import psutil

from bench.framework import QuietVad
from esiaf.audio import Audio
from esiaf.formats import AudioFormat
from esiaf_services.vad.service import VadSettings

FORMAT = AudioFormat(16000, "int16", channels=1)
CHUNK_NS = 50_000_000


def chunk(stream_id: str) -> Audio:
    return Audio("grabber/audio", stream_id, "bench", 1, 10**18, 10**18 + CHUNK_NS, FORMAT, b"\0\0" * 800)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--streams", type=int, default=10_000)
    parser.add_argument("--max-streams", type=int, default=256, help="the vad's max_streams setting")
    args = parser.parse_args()
    vad = QuietVad(VadSettings(name="vad", max_streams=args.max_streams))
    vad.setup()
    vad.on_audio(chunk("warm-up"))  # the model's first run allocates its buffers
    process = psutil.Process()
    before = process.memory_info().rss
    for i in range(args.streams):
        vad.on_audio(chunk(f"s{i}"))
    grown = (process.memory_info().rss - before) / 2**20
    print(f"{args.streams} stream names at max_streams {args.max_streams}: {len(vad.segmenters)} kept, "
          f"{vad.info.get('forgotten_streams', 0)} forgotten, resident memory {grown:+.1f} MB")


if __name__ == "__main__":
    main()

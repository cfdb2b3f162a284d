"""A recording's files (no pipeline): rotation by size into files the mcap package reads, and a
full disk (/dev/full) met mid-recording stopping it with one line."""
from __future__ import annotations

import random
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.mcap_writer import RotatingWriter, next_part


def chunk(n: int) -> pb.AugmentedAudio:
    """50 ms of 16 kHz int16 mono noise, which compresses as little as audio does."""
    return pb.AugmentedAudio(sequence=n, start_ns=n * 50_000_000, end_ns=(n + 1) * 50_000_000,
                             payload=random.Random(n).randbytes(1600))


def test_files_rotate_by_size_each_whole(tmp_path):
    writer = RotatingWriter(tmp_path / "s.mcap", max_bytes=100_000)
    for n in range(400):
        writer.write("grabber/audio", chunk(n), n * 50_000_000)
    writer.close()
    assert not writer.failed and len(writer.paths) >= 3
    assert writer.paths[1] == tmp_path / "s-2.mcap" and next_part(tmp_path / "s.mcap") == len(writer.paths) + 1
    sequences = []
    for path in writer.paths:
        with path.open("rb") as handle:
            reader = make_reader(handle, decoder_factories=[DecoderFactory()])
            assert reader.get_summary() is not None
            sequences += [decoded.sequence for *_, decoded in reader.iter_decoded_messages()]
    assert sequences == list(range(400))


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_full_disk_mid_recording_stops_it_with_one_line(capsys):
    writer = RotatingWriter(Path("/dev/full"), max_bytes=1_000_000)  # 125 kB chunks: flushed mid-recording
    for n in range(400):
        writer.write("grabber/audio", chunk(n), n * 50_000_000)
    writer.close()
    assert "No space left on device" in writer.failed
    assert writer.messages < 400  # the writes after the failure were dropped
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "recording stopped" in lines[0]

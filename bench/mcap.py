"""The recorder's cost, and whether a replay reproduces what was recorded (docs/recording.md).

    python bench/mcap.py [--repeat 5] [--realtime] [--input examples/robocup_scene.flac] [--array respeaker4]

Plays the 4-channel scene ``--repeat`` times over (one file, written here) through ``esiaf run --fast
--record``: the recorder says the CPU time it spent from its first chunk to its finished file and how
much audio it recorded, scaled here to CPU per hour of audio (the target: at most 2 % of one core, i.e.
72 CPU-s per hour). Then replays the recording with ``esiaf run --input REC.mcap --fast --diff`` and
counts the differences between the recorded and the replayed fused results (the target: none).
Prints ``name=value`` lines.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import soundfile  # noqa: E402

from esiaf.tools.testing import free_port  # noqa: E402

RECORDED = re.compile(r"recorded (\d+) messages \(([\d.]+) s of audio, ([\d.]+) CPU-s")
DIFFERENCES = re.compile(r"diff: (\d+) recorded utterances, (\d+) replayed, (\d+) difference")


def esiaf_run(workdir: Path, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "esiaf", "run", "--grammar", "robocup", "--port",
                           str(free_port()), "--workdir", str(workdir), *args], cwd=REPO, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=3600)
    if done.returncode != 0:
        raise SystemExit(f"esiaf run failed ({done.returncode}): {done.stderr[-2000:]}")
    return done, time.monotonic() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=REPO / "examples" / "robocup_scene.flac")
    parser.add_argument("--array", default="respeaker4")
    parser.add_argument("--repeat", type=int, default=5, help="plays of the input, one after the other")
    parser.add_argument("--without", default="emotion,gender,voiceid", help="esiaf run --without (lighter runs)")
    parser.add_argument("--realtime", action="store_true", help="record in real time (default: --fast), where "
                        "each chunk wakes the recorder on its own")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="esiaf-bench-mcap-") as tmp:
        folder = Path(tmp)
        audio, rate = soundfile.read(str(args.input), dtype="int16", always_2d=True)
        scene = folder / "scene.wav"
        soundfile.write(str(scene), np.concatenate([audio] * args.repeat), rate, subtype="PCM_16")
        recording = folder / "scene.mcap"
        options = ["--array", args.array, *(["--without", args.without] if args.without else [])]
        recorded, record_s = esiaf_run(folder / "record", "--input", str(scene), "--record", str(recording), *options,
                                       *([] if args.realtime else ["--fast"]))
        found = RECORDED.search(recorded.stderr)
        if found is None:
            raise SystemExit(f"the recorder said nothing of its cost: {recorded.stderr[-2000:]}")
        messages, audio_s, cpu_s = int(found[1]), float(found[2]), float(found[3])
        replayed, replay_s = esiaf_run(folder / "replay", "--input", str(recording), "--diff", "--fast", *options)
        compared = DIFFERENCES.search(replayed.stdout)
        if compared is None:
            raise SystemExit(f"the replay printed no diff: {replayed.stdout[-2000:]}")
        print(f"mode={'realtime' if args.realtime else 'fast'}")
        print(f"channels={audio.shape[1]}")
        print(f"audio_s={audio_s:.1f}")
        print(f"messages={messages}")
        print(f"file_mb={recording.stat().st_size / 1e6:.2f}")
        print(f"mb_per_hour={recording.stat().st_size / 1e6 * 3600 / audio_s:.0f}")
        print(f"recorder_cpu_s={cpu_s:.2f}")
        print(f"recorder_cpu_s_per_hour={cpu_s * 3600 / audio_s:.1f}")
        print(f"recorder_core_percent={100 * cpu_s / audio_s:.2f}")
        print(f"record_run_s={record_s:.1f}")
        print(f"replay_run_s={replay_s:.1f}")
        print(f"recorded_utterances={compared[1]}")
        print(f"replayed_utterances={compared[2]}")
        print(f"differences={compared[3]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

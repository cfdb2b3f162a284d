"""The denoiser's share on the RoboCup harness' rooms, without the pipeline: the oracle row (each
question's true segment of the first microphone, ± 0.2 s, decoded by the recogniser with the
RoboCup grammar) on the raw microphone and on the same microphone denoised, side by side, in one run.

The rooms are those of ``esiaf eval robocup`` (the same seed renders the same rooms, talkers, babble,
kitchen noise and SNR); the denoiser is the service's own filter (esiaf_services/denoiser/filter.py:
DeepFilterNet 3), fed each question's segment in 20 ms chunks and flushed at its end, one segment
after the other, as the service does with the vad's utterances. CPU is this process's CPU time for
the denoising, per second of audio denoised.

    python -m bench.denoise [--runs 3] [--seed 1] [--arrays pepper4,respeaker4] [--atten-lim-db 100]

Ends with ``name=value`` lines: ``oracle_raw``, ``oracle_denoised`` (shares of the questions
recognised), ``denoiser_cpu_per_audio_s``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.scenes import render  # noqa: E402
from esiaf.tools import evaluation  # noqa: E402
from esiaf.tools.robocup_scoring import Question, oracle  # noqa: E402
from esiaf_services.denoiser.filter import ChannelFilter  # noqa: E402

CHUNK = 320  # 20 ms at 16 kHz, as the grabber sends


def denoised(samples: np.ndarray, rate: int, questions: list[Question], atten_lim_db: float) -> np.ndarray:
    """``samples`` with each question's segment (as ``oracle`` cuts it) denoised, in order, by one filter."""
    f = ChannelFilter(rate, atten_lim_db)
    out = np.zeros_like(samples)
    for question in questions:
        first, last = int(max(0.0, question.start_s - 0.2) * rate), int((question.end_s + 0.2) * rate)
        segment = samples[first:last]
        out[first:last] = np.concatenate([f.process(segment[i:i + CHUNK]) for i in range(0, len(segment), CHUNK)]
                                         + [f.flush()])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="rooms per array (default 3)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--arrays", default="pepper4,respeaker4")
    parser.add_argument("--atten-lim-db", type=float, default=100.0)
    args = parser.parse_args(argv)
    if not evaluation.DATA.is_dir():
        print(f"bench: shared data not found at {evaluation.DATA}", file=sys.stderr)
        return 2
    questions = evaluation.read_questions_and_answers(evaluation.DATA)
    recogniser = evaluation.oracle_recogniser([])
    work = Path(tempfile.mkdtemp(prefix="esiaf-bench-denoise-"))
    right = {"raw": 0, "denoised": 0}
    asked_in_all, cpu_s, audio_s = 0, 0.0, 0.0
    for array in args.arrays.split(","):
        for index in range(args.runs):
            scene, games, snr_db = evaluation.make_scene(index, args.seed, array, (5.0, 15.0), evaluation.DATA,
                                                         work, questions)
            signals, truth = render(scene)
            asked = [Question(game, u["text"], u["azimuth_deg"], u["start_s"], u["end_s"])
                     for game, u in zip(games, truth["utterances"], strict=True)]
            raw = oracle(signals, asked, scene.sample_rate_hz, recogniser)
            started = time.process_time()
            clean = denoised(signals[:, 0].astype(np.float32), scene.sample_rate_hz, asked, args.atten_lim_db)
            cpu_s += time.process_time() - started
            audio_s += sum(q.end_s - q.start_s + 0.4 for q in asked)
            with_denoiser = oracle(clean[:, None], asked, scene.sample_rate_hz, recogniser)
            right["raw"] += raw
            right["denoised"] += with_denoiser
            asked_in_all += len(asked)
            print(f"{array} run {index + 1}: SNR {snr_db:.1f} dB, RT60 {scene.rt60_s:.2f} s: oracle {raw}/10 raw, "
                  f"{with_denoiser}/10 denoised", flush=True)
    print(f"oracle_raw={right['raw'] / asked_in_all:.3f}")
    print(f"oracle_denoised={right['denoised'] / asked_in_all:.3f}")
    print(f"denoiser_cpu_per_audio_s={cpu_s / audio_s:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

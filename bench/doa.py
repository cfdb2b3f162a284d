"""SSL per DOA algorithm: CPU seconds per second of 4-channel audio, and angle error, in one run.

Scenes: the accuracy scene of the tests (esiaf_services.ssl.offline.accuracy_scene: six CMU ARCTIC
utterances from 0/90/180/270/30/200°, 1.5 m away, RT60 0.4 s, kitchen noise from 120° 10 dB below
the speech), rendered once per array (Pepper and ReSpeaker). Every algorithm runs the real ssl
component's frame loop (128 ms frames, nfft 256, 300-5000 Hz, background bin selection) over the
same audio; CPU is this process's CPU time for it. FRIDA is very slow: it gets only the first
``--frida-seconds`` of each scene (its error figures are on those utterances only).

    python -m bench.doa [--arrays pepper4,respeaker4] [--algorithms NormMUSIC,SRP,...] [--frida-seconds 6]

Ends with ``name=value`` lines: ``<array>_<algorithm>_cpu_per_audio_s``, ``..._median_error_deg``,
``..._within_15``, ``..._located_share``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.scenes import render  # noqa: E402
from esiaf.tools.testing import SHARED_DATA  # noqa: E402
from esiaf_services.ssl.doa import ALGORITHMS  # noqa: E402
from esiaf_services.ssl.offline import accuracy_scene, localise, score  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arrays", default="pepper4,respeaker4")
    parser.add_argument("--algorithms", default=",".join(ALGORITHMS))
    parser.add_argument("--frida-seconds", type=float, default=6.0, help="audio FRIDA gets (0 = all)")
    parser.add_argument("--data", type=Path, default=SHARED_DATA, help="the shared data folder")
    args = parser.parse_args(argv)
    if not (args.data / "speech" / "cmu_arctic").is_dir():
        print(f"bench: shared data not found at {args.data} (--data)", file=sys.stderr)
        return 2
    figures: dict[str, float] = {}
    print(f"{'array':<11} {'algorithm':<10} {'audio s':>8} {'CPU s/s':>8} {'median°':>8} {'≤15°':>6} {'located':>8}")
    for array in args.arrays.split(","):
        signals, truth = render(accuracy_scene(array, args.data))
        rate = truth["sample_rate_hz"]
        for algorithm in args.algorithms.split(","):
            audio = signals
            if algorithm.upper() == "FRIDA" and args.frida_seconds:
                audio = signals[:int(args.frida_seconds * rate)]
            started = time.process_time()
            frames = localise(audio, rate, array=array, algorithm=algorithm)
            cpu_s = time.process_time() - started
            seconds = len(audio) / rate
            utterances = [u for u in truth["utterances"] if u["end_s"] <= seconds]
            result = score(frames, utterances)
            key = f"{array}_{algorithm}"
            figures.update({f"{key}_cpu_per_audio_s": cpu_s / seconds,
                            f"{key}_median_error_deg": result["median_error_deg"],
                            f"{key}_within_15": result["within_15"],
                            f"{key}_located_share": result["located_share"]})
            print(f"{array:<11} {algorithm:<10} {seconds:8.1f} {cpu_s / seconds:8.3f} "
                  f"{result['median_error_deg']:8.1f} {result['within_15']:6.2f} {result['located_share']:8.2f}",
                  flush=True)
    for name, value in figures.items():
        print(f"{name}={value:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the vad hears in the canceller's output while the robot talks: the robot's residual, or the babble.

Reads a talk part of ``bench/robot_speaks.py`` (its ``--workdir``'s ``talk/``: ``scene.flac``, ``robot.wav``,
``babble.wav`` and a run's ``fused.json``), renders the same scene again without the babble (the robot's echo
alone, at the same scale: the echo sets the -3 dBFS peak), and runs both through the service's canceller
offline (``StreamCanceller`` and the speex backend at the service's defaults, the reference fed 50 ms
ahead as the player publishes it). It prints:

- the canceller's output level (dBFS over the channels, 32 ms windows, from 10 s on) while the robot speaks
  and in its pauses, with the babble and without it: where the two are alike, the babble is what is left;
- per fused result of the run (``source`` as fusion tagged it): how far the canceller's output follows the
  reference it cancelled, ``follow``: the correlation of the output's and the lined-up reference's log band
  energies (16 bands 150-6000 Hz, 16 ms frames, each band's mean over the segment taken off; frames where
  the reference is within 30 dB of its loudest in the segment). The robot's residual is the reference
  filtered, so it follows it; a voice that is not the robot's does not;
- with ``--rooms SEED:RUN,...``: the same measure over the true spans of the questions the robot overlaps in
  ``esiaf eval robocup --robot-speaks`` rooms (rendered here, as the harness renders them).

    nice -n 10 python -m bench.talk_residual WORKDIR/talk [--run default] [--rooms 1:0,1:1,2:0,2:1]
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

FS = 16000
FRAME = 256  # 16 ms
EDGES = np.geomspace(150.0, 6000.0, 17)


def cancel(mics: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The service's canceller over int16 ``mics``: its published output and the reference as it lined it up."""
    from esiaf_services.aec.backends import SpeexCanceller
    from esiaf_services.aec.core import StreamCanceller

    lined_up: list[np.ndarray] = []

    class Recording(StreamCanceller):
        def _run(self, blocks: int) -> np.ndarray:
            lined_up.append(self._pending_reference[:blocks * self.canceller.block_frames].copy())
            return super()._run(blocks)

    channels = mics.shape[1]
    backend = SpeexCanceller(channels, FS, suppress_residual=True, residual_db=-40, residual_active_db=0, judge=True)
    stream = Recording(backend, FS, max_delay_ms=400.0, fit_min_s=0.5, retrain_passes=2, outlier_ms=0.5)
    chunk, out = FS // 20, []
    stream.add_reference(0, reference[:chunk])
    for first in range(0, len(mics), chunk):
        ahead = first + chunk
        stream.add_reference(ahead * 10**9 // FS, reference[ahead:ahead + chunk])
        out.append(stream.process(first * 10**9 // FS, mics[first:first + chunk]))
    lined_up.append(stream._pending_reference.copy())
    out.append(stream.flush())
    output = np.concatenate(out)[:len(mics), :channels].astype(np.float64) / 32768
    return output, np.concatenate(lined_up)[:len(mics)].astype(np.float64) / 32768


def band_levels(x: np.ndarray) -> np.ndarray:
    """(frames, 16) dB; ``x`` (samples,) or (samples, channels): the channels' band energies averaged."""
    x = x[:, None] if x.ndim == 1 else x
    n = len(x) // FRAME
    frames = x[:n * FRAME].reshape(n, FRAME, -1) * np.hanning(FRAME)[None, :, None]
    power = np.mean(np.abs(np.fft.rfft(frames, axis=1)) ** 2, axis=2)
    freqs = np.fft.rfftfreq(FRAME, 1 / FS)
    bands = np.stack([power[:, (freqs >= lo) & (freqs < hi)].sum(1) for lo, hi in itertools.pairwise(EDGES)], 1)
    return 10 * np.log10(bands + 1e-10)


def follow(out_bands: np.ndarray, ref_bands: np.ndarray, start_s: float, end_s: float) -> float:
    a, b = int(start_s * FS / FRAME), int(end_s * FS / FRAME)
    lo, lr = out_bands[a:b], ref_bands[a:b]
    if not len(lr):
        return float("nan")
    loud = 10 * np.log10(np.sum(10 ** (lr / 10), axis=1))
    keep = loud > loud.max() - 30
    if keep.sum() < 5:
        return float("nan")
    x, y = (lo - lo.mean(0))[keep].ravel(), (lr - lr.mean(0))[keep].ravel()
    x, y = x - x.mean(), y - y.mean()
    spread = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / spread) if spread > 0 else float("nan")  # an output of digital silence


def levels(output: np.ndarray, reference: np.ndarray) -> dict[str, list[float]]:
    hop = 512
    n = len(reference) // hop
    level = 10 * np.log10(np.mean(output[:n * hop].reshape(n, hop, -1) ** 2, axis=(1, 2)) + 1e-12)
    ref = 10 * np.log10(np.mean(reference[:n * hop].reshape(n, hop) ** 2, axis=1) + 1e-12)
    late = np.arange(n) * hop / FS > 10.0
    speaking, pause = late & (ref > ref.max() - 30), late & (ref < ref.max() - 60)
    return {"speaking": [round(float(v), 1) for v in np.percentile(level[speaking], [10, 50, 90])],
            "pause": [round(float(v), 1) for v in np.percentile(level[pause], [10, 50, 90])]}


def echo_alone(talk: Path, seed: int, array: str) -> np.ndarray:
    """The talk's scene rendered again with the babble 70 dB down (bench/robot_speaks.py's talk_part)."""
    from esiaf.scenes import NoiseSource, Scene, SpeechSource, render
    scene = Scene(array=array, room_m=(7.5, 7.0, 3.0), rt60_s=0.45, array_position_m=(3.7, 3.4, 1.2),
                  array_heading_deg=30.0,
                  speech=[SpeechSource(clip=str(talk / "robot-echo.wav"), text="(the robot)", azimuth_deg=0.0,
                                       distance_m=0.07, elevation_deg=-45.0)],
                  noise=[NoiseSource(clip=str(talk / "babble.wav"), azimuth_deg=20.0, distance_m=2.5, snr_db=70.0)],
                  tail_s=1.0, seed=seed)
    signals, _ = render(scene)
    return np.round(signals * 32767).astype(np.int16)


def rooms(spec: str) -> list[tuple[str, float, float, float]]:
    """(room, start, end, follow) of the questions the robot overlaps in the harness's rooms SEED:RUN."""
    import soundfile

    from esiaf.scenes import render
    from esiaf.tools import evaluation as ev
    questions = ev.read_questions_and_answers(ev.DATA)
    rows = []
    for item in filter(None, spec.split(",")):
        seed, index = (int(v) for v in item.split(":"))
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            scene, _, _ = ev.make_scene(index, seed, "respeaker4", (5.0, 15.0), ev.DATA, work, questions)
            ev.robot_speaks(scene, questions, work)
            signals, truth = render(scene)
            robot = soundfile.read(str(work / "robot.wav"))[0]
        output, lined_up = cancel(np.round(signals * 32767).astype(np.int16), robot)
        out_bands, ref_bands = band_levels(output), band_levels(lined_up)
        for u in truth["utterances"]:
            first, last = int((u["start_s"] - ev.ROBOT_DELAY_S) * FS), int((u["end_s"] - ev.ROBOT_DELAY_S) * FS)
            part = np.abs(robot[max(first, 0):max(last, 0)])  # bench/robot_speaks.py's overlapped()
            if len(part) and np.mean(part > 0.02 * np.max(np.abs(robot))) > 0.1:
                rows.append((f"seed {seed} room {index + 1}", u["start_s"], u["end_s"],
                             follow(out_bands, ref_bands, u["start_s"], u["end_s"])))
    return rows


def main(argv: list[str] | None = None) -> int:
    import soundfile
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("talk", type=Path, help="a robot_speaks talk directory (WORKDIR/talk)")
    parser.add_argument("--run", default="default", help="the run directory in it with fused.json")
    parser.add_argument("--seed", type=int, default=1, help="the talk's seed (its scene's)")
    parser.add_argument("--array", default="respeaker4")
    parser.add_argument("--rooms", default="", help="SEED:RUN,... harness rooms whose questions to measure too")
    args = parser.parse_args(argv)
    reference = soundfile.read(str(args.talk / "robot.wav"))[0]
    scene = soundfile.read(str(args.talk / "scene.flac"), dtype="int16", always_2d=True)[0]
    output, lined_up = cancel(scene, reference)
    alone, _ = cancel(echo_alone(args.talk, args.seed, args.array), reference)
    print(f"output dBFS p10/p50/p90 with the babble: robot speaking {levels(output, lined_up)['speaking']}, "
          f"in its pauses {levels(output, lined_up)['pause']}; the echo alone: robot speaking "
          f"{levels(alone, lined_up)['speaking']}")
    out_bands, alone_bands, ref_bands = band_levels(output), band_levels(alone), band_levels(lined_up)
    fused = json.loads((args.talk / args.run / "fused.json").read_text())
    values: dict[str, list[float]] = {"person": [], "robot": [], "echo alone": []}
    for f in fused:
        value = follow(out_bands, ref_bands, f["start_s"], f["end_s"])
        value_alone = follow(alone_bands, ref_bands, f["start_s"], f["end_s"])
        values[str(f.get("source"))].append(value)
        values["echo alone"].append(value_alone)
        print(f"talk {f['start_s']:7.2f}-{f['end_s']:7.2f} s {f.get('source'):6} overlap {f['playback_overlap']:.2f} "
              f"follow {value:+.2f} (the echo alone {value_alone:+.2f})")
    for name, found in values.items():
        found = [v for v in found if np.isfinite(v)]
        if found:
            print(f"talk segments tagged {name}: follow min/median/max {min(found):+.2f} / {np.median(found):+.2f} / "
                  f"{max(found):+.2f} ({len(found)})" if name != "echo alone" else
                  f"the same spans, the echo alone: follow min/median/max {min(found):+.2f} / "
                  f"{np.median(found):+.2f} / {max(found):+.2f} ({len(found)})")
    questions = rooms(args.rooms)
    for room, start, end, value in questions:
        print(f"{room} question {start:6.2f}-{end:6.2f} s follow {value:+.2f}")
    if questions:
        found = [v for *_, v in questions if np.isfinite(v)]
        print(f"questions over the robot: follow min/median/max {min(found):+.2f} / {np.median(found):+.2f} / "
              f"{max(found):+.2f} ({len(found)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

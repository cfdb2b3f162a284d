"""Echo cancellation on a simulated robot head: ERLE, double talk, delay and drift, recovery, CPU.

The scene (pyroomacoustics, one room per array, RT60 0.4 s): the robot's loudspeaker 7 cm from the
centre of its head's microphone array (in front, 5 cm below), saying flite sentences (voice kal16)
with short pauses for ``--seconds`` minus a 5 s pause two thirds in (the player stops, then starts
again); a person 1.5 m away at 60° asking RoboCup@Home questions (flite slt/awb/rms) every 8 s,
most of them while the robot speaks; babble (four voices) at 2.5 m, 200°. At the first microphone
the person is 10 dB below the robot's echo and the babble 10 dB below the person; every microphone
has a sensor noise 60 dB below the echo.

The loudspeaker's reference is what the player published: stamped on its own sample grid. The echo
reaches the microphones ``delay_ms`` later than the stamps say and the player's clock runs ``ppm``
fast (the reference resampled by 1 + ppm/1e6 before it is played); neither is told to the canceller.

Per backend and condition:

- ``erle_db``: echo return loss enhancement on the echo alone (the far end talking, no person, no
  babble), over the robot's speech from 1 s after it starts to the pause, all channels (energy-weighted:
  the first seconds weigh most); ``erle_median_db`` the median of its values per second there;
  ``erle_late_db`` the same over the 10 s before the pause (drift has moved the echo most there);
  ``erle_restart_db`` over the first 2 s after the player starts again;
- double talk, on the full mix, per question: ``sdr_db`` of the output's first channel against the
  person alone at that microphone (a 32-tap filter allowed, as BSS-eval), next to ``sdr_in_db``
  (before cancellation); ``recognised`` questions (pocketsphinx, RoboCup grammar, the first channel,
  the question's span ± 0.2 s) of ``asked``; ``recognised_clean`` the same questions without the
  robot speaking (the target: >= 80 % of it); ``tdoa_kept`` questions whose mic 0-2 delay (GCC-PHAT)
  in the output matches the person-alone one within one sample (what ssl needs);
- ``cpu_pct``: CPU time of the canceller (alignment included) per second of 4-channel audio, in %
  of one core.

    nice -n 10 python -m bench.aec [--backends speex,webrtc] [--arrays pepper4,respeaker4]
        [--conditions 0:0,120:100,300:-100] [--seconds 60] [--json out.json]

Ends with ``name=value`` lines: ``<array>_<backend>_d<delay>_p<ppm>_<figure>``.
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.tools.testing import SHARED_DATA  # noqa: E402

FS = 16000
ROBOT_VOICE = "kal16"
PERSON_VOICES = ("slt", "awb", "rms")
QUESTION_EVERY_S = 8.0
PAUSE_S = 5.0


@dataclass
class Scene:
    """The parts at the microphones, each (samples, mics) float, and what was played and asked."""

    reference: np.ndarray  # what the player published (its own grid), float mono
    echo: np.ndarray
    person: np.ndarray
    babble: np.ndarray
    noise: np.ndarray
    robot_spans: list[tuple[float, float]]  # seconds: where the robot's voice is, before the pause and after
    questions: list[tuple[str, float, float]]  # text, start_s, end_s (at the microphones)


@dataclass
class Figures:
    array: str
    backend: str
    delay_ms: float
    ppm: float
    erle_db: float = math.nan
    erle_median_db: float = math.nan
    erle_late_db: float = math.nan
    erle_restart_db: float = math.nan
    sdr_in_db: float = math.nan
    sdr_db: float = math.nan
    asked: int = 0
    recognised: int = 0
    recognised_raw: int = 0
    recognised_clean: int = 0
    tdoa_kept: int = 0
    cpu_pct: float = math.nan
    delay_estimated_ms: float = math.nan
    drift_estimated_ppm: float = math.nan
    notes: list[str] = field(default_factory=list)


@functools.cache
def flite(text: str, voice: str) -> np.ndarray:
    from esiaf.scenes import speak
    return speak(text, voice, FS)


def questions_and_answers() -> list[tuple[str, str]]:
    rows = []
    for line in (SHARED_DATA / "robocup" / "questions.tsv").read_text().splitlines():
        fields = line.split("\t")
        if len(fields) >= 3 and fields[0].strip().isdigit():
            rows.append((fields[1].strip(), fields[2].strip()))
    return rows


def robot_track(seconds: float, sentences: list[str], rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """The robot's voice on the player's grid: sentences with 0.2-0.6 s pauses, silent for PAUSE_S from 2/3 on."""
    track = np.zeros(int(seconds * FS))
    pause_at, spans, at, part_start = int(seconds * 2 / 3 * FS), [], int(0.5 * FS), int(0.5 * FS)
    resumed = False
    while at < len(track):
        clip = flite(str(rng.choice(sentences)), ROBOT_VOICE)
        if not resumed and at + len(clip) > pause_at:
            spans.append((part_start / FS, at / FS))
            at = part_start = at + int(PAUSE_S * FS)
            resumed = True
            continue
        clip = clip[:len(track) - at]
        track[at:at + len(clip)] = clip
        at += len(clip) + int(rng.uniform(0.2, 0.6) * FS)
    spans.append((part_start / FS, min(at, len(track)) / FS))
    return track, spans


def render(array: str, seconds: float, delay_ms: float, ppm: float, seed: int) -> Scene:
    import pyroomacoustics as pra
    import soxr
    from scipy.signal import fftconvolve

    from esiaf.arrays import load_array
    from esiaf.tools.evaluation import babble_clip
    rng = np.random.default_rng(seed)
    qa = questions_and_answers()
    reference, robot_spans = robot_track(seconds, [answer for _, answer in qa], rng)
    # what the loudspeaker plays, in the microphones' time: the player's clock is ppm fast, and delayed
    played = soxr.resample(reference, FS * (1 + ppm * 1e-6), FS, quality="VHQ")
    played = np.concatenate([np.zeros(round(delay_ms * FS / 1000)), played])[:len(reference)]
    played = np.pad(played, (0, len(reference) - len(played)))

    person = np.zeros(len(reference))
    questions: list[tuple[str, float, float]] = []
    at = 3.0
    chosen = rng.permutation(len(qa))
    while at + 4.0 < seconds:
        text = qa[int(chosen[len(questions) % len(qa)])][0]
        clip = flite(text, PERSON_VOICES[len(questions) % len(PERSON_VOICES)])
        first = int(at * FS)
        clip = clip[:len(person) - first]
        person[first:first + len(clip)] = clip
        loud = np.flatnonzero(np.abs(clip) > 0.02 * np.max(np.abs(clip)))
        questions.append((text, at + loud[0] / FS, at + loud[-1] / FS))
        at += QUESTION_EVERY_S
    babble_path = Path(f"/tmp/esiaf-bench-aec-babble-{seed}.wav")
    if not babble_path.exists():
        babble_clip(np.random.default_rng([seed, 1]), [answer for _, answer in qa], babble_path, seconds=40.0)
    import soundfile
    babble = soundfile.read(str(babble_path))[0]
    babble = np.tile(babble, int(np.ceil(len(reference) / len(babble))))[:len(reference)]

    room_m = np.array([6.0, 5.0, 3.0])
    centre = np.array([3.0, 2.5, 1.2])
    absorption, max_order = pra.inverse_sabine(0.4, room_m)
    room = pra.ShoeBox(room_m, fs=FS, materials=pra.Material(absorption), max_order=max_order, air_absorption=False)
    room.add_microphone_array(pra.MicrophoneArray(centre[:, None] + load_array(array).positions_m, FS))
    around = [centre + np.array([0.05, 0.0, -0.05]),  # the loudspeaker: 7 cm from the array's centre
              centre + 1.5 * np.array([math.cos(math.radians(60)), math.sin(math.radians(60)), 0.0]),
              centre + 2.5 * np.array([math.cos(math.radians(200)), math.sin(math.radians(200)), 0.0])]
    for position in around:
        room.add_source(position)
    room.compute_rir()

    def at_mics(source: int, signal: np.ndarray) -> np.ndarray:
        return np.stack([fftconvolve(signal, rir[source])[:len(signal)] for rir in room.rir], axis=1)

    echo, person_mics, babble_mics = at_mics(0, played), at_mics(1, person), at_mics(2, babble)
    echo_active = np.zeros(len(reference), dtype=bool)
    for start, end in robot_spans:
        echo_active[int(start * FS):int(end * FS)] = True
    person_active = np.zeros(len(reference), dtype=bool)
    for _, start, end in questions:
        person_active[int(start * FS):int(end * FS)] = True
    echo_power = float(np.mean(echo[echo_active, 0] ** 2))
    person_mics *= math.sqrt(echo_power / 10 / float(np.mean(person_mics[person_active, 0] ** 2)))
    babble_mics *= math.sqrt(echo_power / 100 / float(np.mean(babble_mics[:, 0] ** 2)))
    noise = np.random.default_rng([seed, 2]).normal(0, math.sqrt(echo_power) * 1e-3, echo.shape)
    gain = 10 ** (-3 / 20) / np.max(np.abs(echo + person_mics + babble_mics + noise))
    # the reference keeps the level the player sent: the loudspeaker's and the microphones' gains are unknown
    return Scene(reference * 0.5, echo * gain, person_mics * gain, babble_mics * gain, noise * gain,
                 robot_spans, questions)


# the canceller with a fast start (the aec settings drift_fit_min_s 0.5, retrain_passes 2): the service's default
# and this bench's; SLOW_START is the default before it (StreamCanceller's own), which bench/robot_speaks.py
# --slow-start runs beside it
FAST_START = {"retrain_passes": 2, "fit_min_s": 0.5}
SLOW_START = {"retrain_passes": 0, "fit_min_s": 3.0}


def cancel(backend: str, mics: np.ndarray, reference: np.ndarray, align: bool,
           options: dict | None = None) -> tuple[np.ndarray, float, object]:
    """Runs the canceller over ``mics`` in 50 ms chunks as the service gets them; the output, CPU s, stream.
    ``options``: StreamCanceller's keyword arguments (None: the service's default, FAST_START)."""
    from esiaf_services.aec.backends import BACKENDS
    from esiaf_services.aec.core import StreamCanceller
    pcm = np.clip(np.rint(mics * 32767), -32768, 32767).astype(np.int16)
    stream = StreamCanceller(BACKENDS[backend](mics.shape[1], FS), FS, estimate_delay=align,
                             lead_ms=4.0 if align else 0.0, **(FAST_START if options is None else options))
    chunk = FS // 20
    out = []
    started = time.process_time()
    stream.add_reference(0, reference[:chunk])
    for first in range(0, len(pcm), chunk):
        ahead = first + chunk  # the player publishes a chunk before it is played, so before its echo
        stream.add_reference(ahead * 1_000_000_000 // FS, reference[ahead:ahead + chunk])
        out.append(stream.process(first * 1_000_000_000 // FS, pcm[first:first + chunk]))
    out.append(stream.flush())
    cpu = time.process_time() - started
    return np.concatenate(out)[:len(pcm)].astype(np.float64) / 32768, cpu, stream


def erle_db(before: np.ndarray, after: np.ndarray, start_s: float, end_s: float) -> float:
    first, last = int(start_s * FS), int(end_s * FS)
    return 10 * math.log10(np.sum(before[first:last] ** 2) / max(np.sum(after[first:last] ** 2), 1e-20))


def sdr_db(estimate: np.ndarray, clean: np.ndarray, taps: int = 32) -> float:
    """SDR allowing a short filter on the clean signal (BSS-eval's distortion-allowed projection)."""
    from scipy.linalg import toeplitz
    from scipy.signal import lfilter
    r = np.array([np.dot(clean[:len(clean) - k], clean[k:]) for k in range(taps)])
    c = np.array([np.dot(clean[:len(clean) - k], estimate[k:]) for k in range(taps)])
    h = np.linalg.solve(toeplitz(r) + 1e-9 * r[0] * np.eye(taps), c)
    target = lfilter(h, [1.0], clean)
    return 10 * math.log10(np.sum(target ** 2) / max(np.sum((estimate - target) ** 2), 1e-20))


def tdoa(signals: np.ndarray, a: int, b: int, max_lag: int = 8) -> int:
    """The delay of microphone ``b`` after ``a`` in samples (GCC-PHAT, within ``max_lag``)."""
    n = len(signals)
    spectrum = np.fft.rfft(signals[:, b], 2 * n) * np.conj(np.fft.rfft(signals[:, a], 2 * n))
    correlation = np.fft.irfft(spectrum / (np.abs(spectrum) + 1e-12), 2 * n)
    lags = np.concatenate([correlation[-max_lag:], correlation[:max_lag + 1]])
    return int(np.argmax(lags)) - max_lag


class Recogniser:
    def __init__(self) -> None:
        from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
        from esiaf_services.asr.recognizer import PocketsphinxRecognizer
        self._recogniser = PocketsphinxRecognizer(FS, grammar=ROBOCUP_GRAMMAR)
        self._known: dict[tuple, bool] = {}  # the unprocessed signals' answers, the same for every backend

    def right(self, signal: np.ndarray, text: str, start_s: float, end_s: float, key: tuple = ()) -> bool:
        if key:
            if (*key, start_s) not in self._known:
                self._known[(*key, start_s)] = self.right(signal, text, start_s, end_s)
            return self._known[(*key, start_s)]
        from esiaf.tools.robocup_scoring import normalise
        first, last = int(max(0.0, start_s - 0.2) * FS), int((end_s + 0.2) * FS)
        pcm = (np.clip(signal[first:last], -1, 1) * 32767).astype("<i2").tobytes()
        hypotheses = self._recogniser.recognise(pcm)
        return bool(hypotheses) and normalise(hypotheses[0].text) == normalise(text)


def measure(scene: Scene, array: str, backend: str, delay_ms: float, ppm: float, recogniser: Recogniser,
            align: bool = True, options: dict | None = None) -> Figures:
    figures = Figures(array, backend if align else f"{backend}-unaligned", delay_ms, ppm)
    echo_only = scene.echo + scene.noise
    out, _, stream = cancel(backend, echo_only, scene.reference, align, options)
    (first_start, first_end), (second_start, _) = scene.robot_spans[0], scene.robot_spans[-1]
    figures.erle_db = erle_db(echo_only, out, first_start + 1.0, first_end)
    figures.erle_median_db = float(np.median([erle_db(echo_only, out, at, at + 1.0)
                                              for at in np.arange(first_start + 1.0, first_end - 1.0)]))
    figures.erle_late_db = erle_db(echo_only, out, first_end - 10.0, first_end)
    figures.erle_restart_db = erle_db(echo_only, out, second_start, second_start + 2.0)
    tracker = stream.tracker  # type: ignore[attr-defined]
    if tracker.known:
        figures.delay_estimated_ms = float(tracker.delay_at(np.array(first_end))) / FS * 1000
        figures.drift_estimated_ppm = tracker.drift_ppm
    mix = scene.echo + scene.person + scene.babble + scene.noise
    out, cpu, _ = cancel(backend, mix, scene.reference, align, options)
    figures.cpu_pct = 100 * cpu / (len(mix) / FS)
    clean = scene.person + scene.babble + scene.noise
    sdr_in, sdr_out = [], []
    for text, start, end in scene.questions:
        first, last = int(start * FS), int(end * FS)
        sdr_in.append(sdr_db(mix[first:last, 0], scene.person[first:last, 0]))
        sdr_out.append(sdr_db(out[first:last, 0], scene.person[first:last, 0]))
        figures.asked += 1
        figures.recognised += recogniser.right(out[:, 0], text, start, end)
        figures.recognised_raw += recogniser.right(mix[:, 0], text, start, end, key=(array, delay_ms, ppm, "raw"))
        figures.recognised_clean += recogniser.right(clean[:, 0], text, start, end, key=(array, delay_ms, ppm, "clean"))
        figures.tdoa_kept += abs(tdoa(out[first:last], 0, 2) - tdoa(scene.person[first:last], 0, 2)) <= 1
    figures.sdr_in_db, figures.sdr_db = float(np.mean(sdr_in)), float(np.mean(sdr_out))
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backends", default="speex,webrtc", help="of esiaf_services/aec/backends.py's BACKENDS")
    parser.add_argument("--arrays", default="pepper4,respeaker4")
    parser.add_argument("--conditions", default="0:0,120:100,300:-100",
                        help="DELAY_MS:PPM pairs, comma-separated")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--unaligned", action="store_true", help="also run each backend without the delay tracker")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    conditions = [tuple(float(v) for v in c.split(":")) for c in args.conditions.split(",")]
    recogniser = Recogniser()
    rows: list[Figures] = []
    for array in args.arrays.split(","):
        for delay_ms, ppm in conditions:
            scene = render(array, args.seconds, delay_ms, ppm, args.seed)
            for backend in args.backends.split(","):
                for align in (True, False) if args.unaligned else (True,):
                    row = measure(scene, array, backend, delay_ms, ppm, recogniser, align)
                    rows.append(row)
                    print(f"{row.array:10s} {row.backend:18s} delay {delay_ms:5.0f} ms drift {ppm:+5.0f} ppm: "
                          f"ERLE {row.erle_db:5.1f} dB (median {row.erle_median_db:5.1f}, late "
                          f"{row.erle_late_db:5.1f}, restart "
                          f"{row.erle_restart_db:5.1f}); SDR {row.sdr_in_db:5.1f} -> {row.sdr_db:5.1f} dB; "
                          f"recognised {row.recognised}/{row.asked} (raw {row.recognised_raw}, no robot "
                          f"{row.recognised_clean}); TDOA kept {row.tdoa_kept}/{row.asked}; CPU {row.cpu_pct:.2f} %; "
                          f"delay est {row.delay_estimated_ms:.1f} ms, drift est {row.drift_estimated_ppm:+.0f} ppm",
                          flush=True)
    for row in rows:
        key = f"{row.array}_{row.backend}_d{row.delay_ms:g}_p{row.ppm:g}"
        for name in ("erle_db", "erle_median_db", "erle_late_db", "erle_restart_db", "sdr_db", "recognised",
                     "recognised_clean", "cpu_pct"):
            value = getattr(row, name)
            print(f"{key}_{name}={value:.3f}" if isinstance(value, float) else f"{key}_{name}={value}")
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

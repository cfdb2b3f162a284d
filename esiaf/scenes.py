"""Labelled scenes: angle-labelled multi-channel recordings simulated with pyroomacoustics.

A scene is a shoebox room (size, RT60), a microphone array (any spec of :mod:`esiaf.arrays`)
at a position, speech sources (a clip or a sentence for flite to say; azimuth relative to the array's front, distance,
onset) and noise sources (a clip, azimuth, distance, SNR relative to the speech). Rendering
gives the array's signals and the truth: per utterance its text, speaker, azimuth and where the
speech is (start and end in seconds, the clip's quiet lead and tail (under 2 % of its peak) excluded, plus the travel
time to the array).

Library::

    scene = Scene(array="respeaker4", speech=[SpeechSource(clip="a.wav", text="...", azimuth_deg=90)],
                  noise=[NoiseSource(clip="n.wav", azimuth_deg=0, snr_db=10)])
    signals, truth = render(scene)            # (samples, mics) float, dict
    write(scene, Path("scene.flac"))          # int16 WAV/FLAC + scene.json beside it

Command line (a scene as YAML, with the fields of :class:`Scene`)::

    python -m esiaf.scenes scene.yaml --out scene.flac

SNR: each noise source is scaled so that its power at the first microphone is ``snr_db`` below
the power of all speech at that microphone while anyone speaks.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from esiaf.arrays import ArrayError, load_array
from esiaf.settings import SettingsError, read_yaml_file

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parent.parent
SPEED_OF_SOUND_M_S = 343.0
SPEECH_THRESHOLD = 0.02  # of the clip's peak: quieter samples at its ends are not speech
WALL_MARGIN_M = 0.3


class SceneError(ValueError):
    """A scene that cannot be rendered; the message says why."""


@dataclass
class SpeechSource:
    azimuth_deg: float
    clip: str = ""  # a mono sound file; or leave empty and give `say`
    say: str = ""  # a sentence for flite to speak (needs Debian's flite)
    voice: str = "slt"  # flite voice for `say`
    text: str = ""  # what is said (defaults to `say`)
    speaker: str = ""  # defaults to the voice or the clip's name
    onset_s: float = 0.0
    distance_m: float = 1.5
    elevation_deg: float = 0.0
    gain_db: float = 0.0


@dataclass
class NoiseSource:
    clip: str
    azimuth_deg: float
    distance_m: float = 2.0
    elevation_deg: float = 0.0
    snr_db: float = 10.0


@dataclass
class Scene:
    array: str = "respeaker4"
    room_m: tuple[float, float, float] = (6.0, 5.0, 3.0)
    rt60_s: float = 0.4
    array_position_m: tuple[float, float, float] | None = None  # default: room centre, 1.2 m high
    array_heading_deg: float = 0.0  # where the array's front (0°) points in the room, counter-clockwise from x
    sample_rate_hz: int = 16000
    speech: list[SpeechSource] = field(default_factory=list)
    noise: list[NoiseSource] = field(default_factory=list)
    tail_s: float = 1.0  # after the last speech
    peak_dbfs: float = -3.0  # the mixture is scaled to this peak
    seed: int = 0  # where in a long noise clip the scene's noise starts

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Scene:
        known = set(cls.__dataclass_fields__)
        unknown = set(data) - known
        if unknown:
            raise SceneError(f"unknown scene keys {', '.join(sorted(unknown))}; known: {', '.join(sorted(known))}")
        values = dict(data)
        try:
            values["speech"] = [SpeechSource(**s) for s in data.get("speech", [])]
            values["noise"] = [NoiseSource(**n) for n in data.get("noise", [])]
        except TypeError as exc:
            raise SceneError(f"bad source in scene: {exc}") from None
        return cls(**values)


def _pyroomacoustics():
    try:
        import pyroomacoustics
    except ImportError:
        raise SceneError("rendering scenes needs pyroomacoustics: pip install -e '.[ssl]'") from None
    return pyroomacoustics


def read_clip(path: str | Path, sample_rate_hz: int) -> np.ndarray:
    import soundfile
    import soxr
    try:
        samples, rate = soundfile.read(str(path), dtype="float64", always_2d=True)
    except (RuntimeError, soundfile.LibsndfileError) as exc:
        raise SceneError(f"cannot read clip {path}: {exc}") from None
    if samples.shape[1] != 1:
        raise SceneError(f"clip {path} has {samples.shape[1]} channels; a source is one mono clip")
    mono = samples[:, 0]
    return soxr.resample(mono, rate, sample_rate_hz) if rate != sample_rate_hz else mono


def speak(text: str, voice: str, sample_rate_hz: int) -> np.ndarray:
    """A sentence spoken by flite, as float samples."""
    import soxr
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        from synth_questions import SAMPLE_RATE_HZ, SynthesisError, synthesise_sentence
    finally:
        sys.path.remove(str(REPO / "scripts"))
    try:
        samples = synthesise_sentence(text, voice).astype(np.float64) / 32768.0
    except SynthesisError as exc:
        raise SceneError(str(exc)) from None
    return soxr.resample(samples, SAMPLE_RATE_HZ, sample_rate_hz) if sample_rate_hz != SAMPLE_RATE_HZ else samples


def speech_bounds(samples: np.ndarray) -> tuple[int, int]:
    """First and one-past-last sample louder than SPEECH_THRESHOLD of the clip's peak."""
    loud = np.flatnonzero(np.abs(samples) > SPEECH_THRESHOLD * np.max(np.abs(samples), initial=0.0))
    if not len(loud):
        raise SceneError("a speech clip is silent")
    return int(loud[0]), int(loud[-1]) + 1


def _position(centre: np.ndarray, azimuth_deg: float, elevation_deg: float, distance_m: float,
              room: np.ndarray, what: str) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    point = centre + distance_m * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    if np.any(point < WALL_MARGIN_M) or np.any(point > room - WALL_MARGIN_M):
        raise SceneError(f"{what} at azimuth {azimuth_deg:g}°, {distance_m:g} m from the array lies outside the "
                         f"room of {' x '.join(f'{v:g}' for v in room)} m (or within {WALL_MARGIN_M} m of a wall)")
    return point


def render(scene: Scene) -> tuple[np.ndarray, dict[str, Any]]:
    """The array's signals (samples, mics) as float in [-1, 1) and the truth of the scene."""
    speech, noise, truth = render_parts(scene)
    return speech + noise, truth


def render_parts(scene: Scene) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """What :func:`render` mixes: all speech and all noise at the array, each (samples, mics)."""
    pra = _pyroomacoustics()
    if not scene.speech:
        raise SceneError("a scene needs at least one speech source")
    try:
        array = load_array(scene.array)
    except ArrayError as exc:
        raise SceneError(str(exc)) from None
    fs = scene.sample_rate_hz
    room_dim = np.array(scene.room_m, dtype=float)
    centre = (np.array(scene.array_position_m, dtype=float) if scene.array_position_m is not None
              else np.array([room_dim[0] / 2, room_dim[1] / 2, 1.2]))
    heading = math.radians(scene.array_heading_deg)
    turn = np.array([[math.cos(heading), -math.sin(heading), 0.0], [math.sin(heading), math.cos(heading), 0.0],
                     [0.0, 0.0, 1.0]])
    mics = centre[:, None] + turn @ array.positions_m
    if np.any(mics < 0) or np.any(mics > room_dim[:, None]):
        raise SceneError("the array lies outside the room")
    try:
        absorption, max_order = pra.inverse_sabine(scene.rt60_s, room_dim)
    except ValueError as exc:
        raise SceneError(f"RT60 {scene.rt60_s:g} s is impossible in this room: {exc}") from None

    clips: list[tuple[np.ndarray, np.ndarray, float]] = []
    utterances: list[dict[str, Any]] = []
    for number, source in enumerate(scene.speech):
        if bool(source.clip) == bool(source.say):
            raise SceneError(f"speech source {number + 1}: give exactly one of clip or say")
        clip = read_clip(source.clip, fs) if source.clip else speak(source.say, source.voice, fs)
        clip = clip * 10 ** (source.gain_db / 20)
        first, last = speech_bounds(clip)
        position = _position(centre, source.azimuth_deg + scene.array_heading_deg, source.elevation_deg,
                             source.distance_m, room_dim, f"speech source {number + 1}")
        travel_s = source.distance_m / SPEED_OF_SOUND_M_S
        clips.append((position, clip, source.onset_s))
        utterances.append({
            "text": source.text or source.say, "speaker": source.speaker or (source.voice if source.say else
                                                                               Path(source.clip).stem),
            "azimuth_deg": source.azimuth_deg % 360.0, "elevation_deg": source.elevation_deg,
            "distance_m": source.distance_m,
            "start_s": round(source.onset_s + first / fs + travel_s, 4),
            "end_s": round(source.onset_s + last / fs + travel_s, 4)})
    duration = max(onset + len(clip) / fs for _, clip, onset in clips) + scene.tail_s
    samples = round(duration * fs)

    room = pra.ShoeBox(room_dim, fs=fs, materials=pra.Material(absorption), max_order=max_order,
                       air_absorption=False)
    room.add_microphone_array(pra.MicrophoneArray(mics, fs))
    for position, clip, onset in clips:
        room.add_source(position, signal=clip, delay=onset)
    rng = np.random.default_rng(scene.seed)
    for number, noise_source in enumerate(scene.noise):
        noise = read_clip(noise_source.clip, fs)
        reps = int(np.ceil(samples / len(noise)))
        noise = np.tile(noise, reps) if reps > 1 else noise
        start = int(rng.integers(0, len(noise) - samples + 1))
        room.add_source(_position(centre, noise_source.azimuth_deg + scene.array_heading_deg,
                                  noise_source.elevation_deg, noise_source.distance_m, room_dim,
                                  f"noise source {number + 1}"),
                        signal=noise[start:start + samples])
    premix = room.simulate(return_premix=True)[:, :, :samples]  # (sources, mics, samples)
    if premix.shape[2] < samples:
        premix = np.pad(premix, ((0, 0), (0, 0), (0, samples - premix.shape[2])))
    speech = premix[:len(clips)].sum(axis=0)
    active = np.zeros(samples, dtype=bool)
    for u in utterances:
        active[int(u["start_s"] * fs):int(u["end_s"] * fs)] = True
    speech_power = float(np.mean(speech[0, active] ** 2))
    noise_sum = np.zeros_like(speech)
    for noise_source, noise in zip(scene.noise, premix[len(clips):], strict=True):
        noise_power = float(np.mean(noise[0] ** 2)) or 1e-20
        noise_sum += noise * math.sqrt(speech_power / noise_power * 10 ** (-noise_source.snr_db / 10))
    gain = 10 ** (scene.peak_dbfs / 20) / np.max(np.abs(speech + noise_sum))
    truth = {"array": array.name, "positions_m": array.positions_m.T.round(5).tolist(),
             "sample_rate_hz": fs, "duration_s": round(samples / fs, 4), "room_m": list(map(float, room_dim)),
             "rt60_s": scene.rt60_s, "array_position_m": centre.round(4).tolist(),
             "array_heading_deg": scene.array_heading_deg % 360.0,
             "noise": [{"clip": Path(n.clip).name, "azimuth_deg": n.azimuth_deg % 360.0, "snr_db": n.snr_db,
                        "distance_m": n.distance_m} for n in scene.noise],
             "utterances": utterances}
    return speech.T * gain, noise_sum.T * gain, truth


def write(scene: Scene, out: Path) -> dict[str, Any]:
    """Renders ``scene`` to ``out`` (16-bit WAV or FLAC by suffix) and its truth to ``out`` with .json."""
    import soundfile
    signals, truth = render(scene)
    out.parent.mkdir(parents=True, exist_ok=True)
    soundfile.write(str(out), np.round(signals * 32767).astype(np.int16), scene.sample_rate_hz, subtype="PCM_16")
    truth["audio"] = out.name
    out.with_suffix(".json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth


def load_scene(path: Path) -> Scene:
    try:
        data = read_yaml_file(path)
    except SettingsError as exc:
        raise SceneError(str(exc)) from None
    base = path.resolve().parent  # clip paths are relative to the scene file
    for source in data.get("speech", []) + data.get("noise", []):
        if isinstance(source, dict) and source.get("clip"):
            source["clip"] = str(base / Path(source["clip"]).expanduser())
    return Scene.from_dict(data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m esiaf.scenes", description="Render a labelled scene "
                                     "(YAML) to a multi-channel WAV/FLAC and its truth JSON")
    parser.add_argument("scene", type=Path, help="scene file (YAML with the fields of esiaf.scenes.Scene)")
    parser.add_argument("--out", type=Path, required=True, help="audio to write (.wav or .flac); truth beside it")
    args = parser.parse_args(argv)
    try:
        truth = write(load_scene(args.scene), args.out)
    except SceneError as exc:
        print(f"scenes: {exc}", file=sys.stderr)
        return 2
    print(f"scenes: wrote {args.out} ({truth['duration_s']} s, {len(truth['positions_m'])} channels, "
          f"{len(truth['utterances'])} utterances) and {args.out.with_suffix('.json').name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The SSL component run over in-memory audio, without sockets: for tests, benchmarks and scoring.

:func:`localise` feeds (samples, mics) audio to a real :class:`Ssl` component chunk by chunk, as
the grabber would, and collects what it emits. :func:`score` compares its directions with a
scene's truth.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from esiaf import Audio, AudioFormat
from esiaf.formats import encode
from esiaf.scenes import NoiseSource, Scene, SpeechSource
from esiaf_services.ssl.service import Ssl, SslSettings
from esiaf_services.ssl.tracker import angle_difference_deg

NS = 1_000_000_000
# the accuracy scene: six utterances from 0, 90, 180, 270 and two angles not multiples of 45
ANGLES = (0.0, 90.0, 180.0, 270.0, 30.0, 200.0)
CLIPS = ("arctic_a0010", "cmu_arctic_us_aew_a0001", "cmu_arctic_us_aew_a0002", "cmu_arctic_us_aew_a0003",
         "cmu_arctic_us_axb_a0004", "cmu_arctic_us_axb_a0005")
NOISE_CLIP = "noise/speech_commands_bg/doing_the_dishes.wav"


@dataclass
class Frame:
    start_s: float
    end_s: float
    azimuth_deg: float | None  # None: covered with "nothing"
    confidence: float = 0.0
    source_id: str = ""


def localise(signals: np.ndarray, sample_rate_hz: int, chunk_ms: float = 20.0,
             on_forward: Callable[..., Any] | None = None, reference: np.ndarray | None = None,
             component: list[Ssl] | None = None, **settings: Any) -> list[Frame]:
    """SSL frames of float (samples, mics) audio, times in seconds from its start.

    ``on_forward(topic, audio, **meta)`` sees every chunk the component forwards. ``reference``: what
    the robot's loudspeaker played (float mono, stamped on the same timeline), given on
    ``player/audio`` a chunk ahead of the microphones, as a player publishes it. ``component``: a list
    the Ssl component is appended to (to look at it afterwards).
    """
    if reference is not None:
        settings.setdefault("reference_topic", "player/audio")
    ssl = Ssl(SslSettings(sample_rate_hz=sample_rate_hz, **settings))
    if component is not None:
        component.append(ssl)
    ssl.setup()
    frames: list[Frame] = []

    def emit(kind, span, stream_id=None, **payload):
        start_s, end_s = span[0] / NS, span[1] / NS
        if "nothing" in payload:
            frames.append(Frame(start_s, end_s, None))
        else:
            best = payload["ssl"].directions[0]
            frames.append(Frame(start_s, end_s, best.azimuth_deg, best.probability, best.source_id))

    # the offline run keeps what the service would send to the orchestrator and the beamformer
    ssl.emit = emit  # type: ignore[method-assign]
    ssl.forward = on_forward or (lambda *args, **kwargs: 0)  # type: ignore[method-assign]
    fmt = AudioFormat(sample_rate_hz, "int16", channels=signals.shape[1])
    ints = np.round(np.clip(signals, -1, 1 - 1 / 32768) * 32768).astype(np.int16)
    step = max(1, round(sample_rate_hz * chunk_ms / 1000))
    mono = AudioFormat(sample_rate_hz, "int16", channels=1)
    played = None if reference is None else np.round(np.clip(reference, -1, 1 - 1 / 32768) * 32768).astype(np.int16)
    for sequence, start in enumerate(range(0, len(ints), step), start=1):
        ahead = start + step
        if played is not None and (start == 0 or ahead < len(played)):
            first, part = (0, played[:2 * step]) if start == 0 else (ahead, played[ahead:ahead + step])
            ssl.on_audio(Audio(topic=ssl.settings.reference_topic, stream_id="offline", publisher="player",
                               sequence=sequence, start_ns=first * NS // sample_rate_hz,
                               end_ns=(first + len(part)) * NS // sample_rate_hz, format=mono,
                               payload=encode(part[:, None], mono)))
        chunk = ints[start:start + step]
        end = start + len(chunk)
        audio = Audio(topic=ssl.settings.input_topic, stream_id="offline", publisher="offline", sequence=sequence,
                      start_ns=start * NS // sample_rate_hz, end_ns=end * NS // sample_rate_hz, format=fmt,
                      payload=encode(chunk, fmt))
        audio.meta.end_of_stream = end >= len(ints)
        ssl.on_audio(audio)
    return frames


def score(frames: list[Frame], utterances: list[dict[str, Any]]) -> dict[str, Any]:
    """Angle errors of the speech frames: those within an utterance's speech (per utterance and overall).

    A speech frame covered with "nothing" counts as a miss in ``located_share``, not in the errors.
    """
    per_utterance, errors, speech_frames = [], [], 0
    for u in utterances:
        inside = [f for f in frames if f.start_s >= u["start_s"] and f.end_s <= u["end_s"]]
        speech_frames += len(inside)
        located = [f for f in inside if f.azimuth_deg is not None]
        errs = [angle_difference_deg(f.azimuth_deg, u["azimuth_deg"]) for f in located
                if f.azimuth_deg is not None]  # all of them: located ones have a direction
        errors += errs
        per_utterance.append({"azimuth_deg": u["azimuth_deg"], "frames": len(inside), "located": len(located),
                              "median_error_deg": float(np.median(errs)) if errs else None,
                              "within_15": float(np.mean(np.array(errs) <= 15)) if errs else 0.0})
    errors_arr = np.array(errors)
    return {"speech_frames": speech_frames, "located_share": len(errors) / speech_frames if speech_frames else 0.0,
            "median_error_deg": float(np.median(errors_arr)) if len(errors) else float("nan"),
            "within_15": float(np.mean(errors_arr <= 15)) if len(errors) else 0.0,
            "utterances": per_utterance}



def accuracy_scene(array: str, data: Path) -> Scene:
    """Six CMU ARCTIC utterances one after another (0.3 s apart) from ANGLES, 1.5 m from the array, in a
    6 x 5 x 3 m room with RT60 0.4 s; kitchen noise from 120°, 2 m away, 10 dB below the speech.
    ``data`` is the shared data folder."""
    import soundfile
    speech, onset = [], 0.5
    for angle, name in zip(ANGLES, CLIPS, strict=True):
        clip = data / "speech" / "cmu_arctic" / f"{name}.wav"
        speech.append(SpeechSource(clip=str(clip), azimuth_deg=angle, distance_m=1.5, onset_s=onset, speaker=name))
        onset += soundfile.info(str(clip)).duration + 0.3
    return Scene(array=array, rt60_s=0.4, speech=speech,
                 noise=[NoiseSource(clip=str(data / NOISE_CLIP), azimuth_deg=120.0, distance_m=2.0, snr_db=10.0)])

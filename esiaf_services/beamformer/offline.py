"""The beamformer over in-memory audio, without sockets: for tests and benchmarks.

:func:`snr_gain` steers a :class:`~esiaf_services.beamformer.beam.BeamStream` at the talker of a
rendered scene (its truth says where and when), learning the noise where nobody speaks, and
applies the very same weights, frame by frame, to the scene's speech alone and noise alone: the
SNR at the output against the SNR at the reference microphone, within the speech.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from esiaf.arrays import load_array
from esiaf_services.beamformer.beam import BeamCore, BeamStream


def _follow(shadow: BeamStream, main: BeamStream) -> None:
    shadow.target, shadow.weights, shadow.previous, shadow.fade = main.target, main.weights, main.previous, main.fade


def snr_gain(speech: np.ndarray, noise: np.ndarray, truth: dict[str, Any], **settings: Any) -> dict[str, float]:
    """SNR (dB) at the reference microphone and at the output, over the speech; (samples, mics) inputs."""
    rate = truth["sample_rate_hz"]
    core = BeamCore(load_array(truth["array"]), rate, **settings)
    main, alone_speech, alone_noise = core.stream(), core.stream(), core.stream()
    talking = np.full(len(speech), np.nan)
    for u in truth["utterances"]:
        talking[int(u["start_s"] * rate):int(u["end_s"] * rate)] = u["azimuth_deg"]
    outputs: list[list[np.ndarray]] = [[], []]
    for start in range(0, len(speech) - core.hop + 1, core.hop):
        azimuth = talking[start + core.hop - 1]
        main.steer(None if math.isnan(azimuth) else float(azimuth))
        for shadow in (alone_speech, alone_noise):
            _follow(shadow, main)
        main.process(speech[start:start + core.hop] + noise[start:start + core.hop],
                     noise_only=bool(math.isnan(azimuth)))
        outputs[0].append(alone_speech.process(speech[start:start + core.hop]))
        outputs[1].append(alone_noise.process(noise[start:start + core.hop]))
    out_speech, out_noise = np.concatenate(outputs[0]), np.concatenate(outputs[1])
    inside = ~np.isnan(talking[:len(out_speech)])
    ref = core.reference

    def snr(s: np.ndarray, n: np.ndarray) -> float:
        return 10 * math.log10(np.mean(s[inside] ** 2) / np.mean(n[inside] ** 2))

    before = snr(speech[:len(out_speech), ref], noise[:len(out_speech), ref])
    after = snr(out_speech, out_noise)
    return {"snr_in_db": before, "snr_out_db": after, "gain_db": after - before}

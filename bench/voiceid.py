"""Voiceid: speaker identification on EmoDB, clean and through a simulated room; CPU and latency.

Every EmoDB utterance (10 speakers, 535, acted emotions) is cut to its speech span
(``esiaf.scenes.speech_bounds``, as a VAD segment would be) and embedded by the numpy encoder.

- closed set: each speaker enrolled from 3 neutral utterances (the first by file name), every
  other utterance identified among the 10 (``closed_accuracy``);
- open set: 7 speakers enrolled, 3 kept unknown, for each of 3 rotations of the unknown three;
  genuine trials = an enrolled speaker's utterance scored against its own voice, impostor
  trials = an unknown speaker's utterance's best score over the 7. ``open_eer`` is the equal
  error rate of the pooled trials, ``open_eer_threshold`` the score where it lies;
- ``neutral_*``: the same with the neutral utterances only (enrolment and trials): the voiceid's
  default ``threshold`` is ``neutral_open_eer_threshold`` (clean), rounded: a robot hears
  commands, not acted anger;
- ``room_*``: the same after a 6×5×3 m room (RT60 0.4 s, pyroomacoustics), speaker 1.5 m and
  the kitchen noise (doing_the_dishes.wav) 2 m from the microphone, the noise scaled to 10 dB
  below the speech at the microphone; enrolment and trials both in the room;
- ``cpu_s_per_speech_s``: encoder CPU time (process time) per second of speech, in this process;
- with ``--variants``, a table of the figures (closed-set accuracy, open-set EER and its threshold,
  all emotions and neutral only, clean and in the room) for each variant of ``VARIANTS``: partial
  windows or the whole utterance, cohort centring, adaptive s-norm, perturbed enrolment copies.
  The cohort is ``esiaf_services/voiceid/cohort.py``'s: the shared data's real non-EmoDB speech and
  flite voices, none of them an EmoDB speaker;
- with ``--room-enrolment``, the room's trials against a clean enrolment (as a WAV enrolment would
  be made), without and with reverberant noisy copies of each enrolment utterance in rooms unlike
  the test room (``ROOM_COPIES``);
- ``latency_p50_ms``: with ``--pipeline``, a few utterances played in real time through
  grabber → vad → voiceid → orchestrator: arrival of the fused result minus (end of the segment's
  speech + the VAD's hang-over), as bench/emotion.py.

    python bench/voiceid.py [--pipeline] [--variants] [--room-enrolment]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import soundfile
import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

from esiaf.scenes import speech_bounds  # noqa: E402
from esiaf.tools.testing import SHARED_DATA  # noqa: E402
from esiaf_services.voiceid.encoder import RESEMBLYZER_PARTIALS_PER_S, VoiceEncoder  # noqa: E402
from esiaf_services.voiceid.scoring import VoiceBook  # noqa: E402

ENROL_UTTERANCES = 3
UNKNOWN_SPEAKERS = 3
SNR_DB = 10.0


def load_emodb() -> list[tuple[str, str, bool, np.ndarray]]:
    """(file name, speaker, neutral, speech-span samples) of every utterance."""
    wavs = SHARED_DATA / "emodb" / "wav"
    if not wavs.is_dir():
        raise SystemExit(f"bench: {wavs} is absent (the shared data folder belongs beside the repository)")
    out = []
    for path in sorted(wavs.glob("*.wav")):
        samples, _ = soundfile.read(path, dtype="float32")
        first, last = speech_bounds(samples)
        out.append((path.name, path.name[:2], path.name[5] == "N", samples[first:last]))
    return out


def through_room(utterances: list[np.ndarray]) -> list[np.ndarray]:
    import pyroomacoustics as pra
    room_m = np.array([6.0, 5.0, 3.0])
    absorption, max_order = pra.inverse_sabine(0.4, room_m)
    room = pra.ShoeBox(room_m, fs=16000, materials=pra.Material(absorption), max_order=max_order)
    mic = np.array([3.0, 2.5, 1.2])
    room.add_microphone(mic)
    room.add_source(mic + np.array([1.5, 0.0, 0.3]))  # numpy: elementwise
    room.add_source(mic + np.array([-1.0, 1.7, -0.2]))
    room.compute_rir()
    speech_rir, noise_rir = room.rir[0][0], room.rir[0][1]
    noise, _rate = soundfile.read(SHARED_DATA / "noise" / "speech_commands_bg" / "doing_the_dishes.wav",
                                 dtype="float32")
    noise = np.convolve(noise if noise.ndim == 1 else noise[:, 0], noise_rir)
    rng = np.random.default_rng(0)
    out = []
    for samples in utterances:
        speech = np.convolve(samples, speech_rir)[:samples.size + 1600]
        start = rng.integers(0, noise.size - speech.size)
        clip = noise[start:start + speech.size]
        gain = np.sqrt(np.mean(speech ** 2) / np.mean(clip ** 2) / 10 ** (SNR_DB / 10))
        out.append((speech + gain * clip).astype(np.float32))
    return out


def eer(genuine: np.ndarray, impostor: np.ndarray) -> tuple[float, float]:
    """Equal error rate and the threshold where false rejections = false acceptances."""
    best, rate = (1.0, 0.0), 0.5
    for threshold in np.unique(np.concatenate([genuine, impostor])):
        false_reject, false_accept = np.mean(genuine < threshold), np.mean(impostor >= threshold)
        gap = abs(false_reject - false_accept)
        if gap < best[0]:
            best, rate = (gap, threshold), (false_reject + false_accept) / 2
    return float(rate), float(best[1])


def enrolment(speakers: list[str], neutral: list[bool]) -> dict[str, list[int]]:
    """Speaker → indices of its enrolment utterances: the first ENROL_UTTERANCES neutral ones."""
    return {s: [i for i, (sp, n) in enumerate(zip(speakers, neutral, strict=True)) if sp == s and n][:ENROL_UTTERANCES]
            for s in sorted(set(speakers))}


def evaluate(names: list[str], speakers: list[str], neutral: list[bool], embeddings: np.ndarray,
             book: Callable[[dict[str, np.ndarray]], VoiceBook] = VoiceBook,
             extra: dict[int, np.ndarray] | None = None, enrol_from: np.ndarray | None = None) -> dict[str, float]:
    """Closed- and open-set figures; ``book`` makes the scorer from the enrolled embeddings, ``extra``
    adds embeddings (e.g. of perturbed copies) to an enrolment utterance's, by its index;
    ``enrol_from``: the enrolment utterances' embeddings are taken from there (e.g. clean) rather
    than from ``embeddings`` (e.g. in the room)."""
    ids = sorted(set(speakers))
    enrol = enrolment(speakers, neutral)
    enrolled = {i for idx in enrol.values() for i in idx}
    trials = [i for i in range(len(names)) if i not in enrolled]
    source = embeddings if enrol_from is None else enrol_from
    voices = {s: np.concatenate([source[idx]] + [extra[i] for i in idx if extra and i in extra]) for s, idx
              in enrol.items()}
    closed = book(voices)
    correct = [max(closed.scores(embeddings[i]).items(), key=lambda kv: kv[1])[0] == speakers[i] for i in trials]
    genuine, impostor = [], []
    for rotation in range(3):
        unknown = set(ids[rotation * UNKNOWN_SPEAKERS:(rotation + 1) * UNKNOWN_SPEAKERS])
        known = book({s: e for s, e in voices.items() if s not in unknown})
        for i in trials:
            scores = known.scores(embeddings[i])
            (impostor.append(max(scores.values())) if speakers[i] in unknown else genuine.append(scores[speakers[i]]))
    rate, threshold = eer(np.array(genuine), np.array(impostor))
    return {"closed_accuracy": float(np.mean(correct)), "closed_trials": len(trials),
            "open_eer": rate, "open_eer_threshold": threshold,
            "open_genuine_trials": len(genuine), "open_impostor_trials": len(impostor)}


def pipeline_latency(files: list[Path]) -> dict[str, float]:
    from esiaf.speech.segmenter import SegmenterParams
    from esiaf_services.emotion.tools.pipeline import EmotionPipeline, build_recording

    class VoicePipeline(EmotionPipeline):  # orchestrator + vad + voiceid, fused on voice_id
        def __init__(self, workdir: Path):
            from esiaf.tools.cli import topic_ready
            from esiaf.tools.launcher import OrchestratorClient, Supervisor, wait_until
            from esiaf.tools.testing import free_port
            self.stream_id = "bench"
            port = free_port()
            self.url = f"http://127.0.0.1:{port}"
            config = workdir / "orchestrator.yaml"
            config.write_text(yaml.safe_dump({"fusions": [{"name": "voice_id", "anchor": "voice_id"}]}))
            self.supervisor = Supervisor(workdir, env={"ESIAF_ORCHESTRATOR_URL": self.url, "ESIAF_STREAM_ID": "bench"})
            self.client = OrchestratorClient(self.url)
            self._start("orchestrator", ["--port", str(port), "--db", str(workdir / "esiaf.db"), "--config",
                                         str(config)], client_ready=self.client.healthy,
                        env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": "0", "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"})
            for service in ("voiceid", "vad"):
                self._start(service, [])
            wait_until(lambda: topic_ready(self.client, "vad/speech", 1), self.supervisor,
                       "voiceid to subscribe to vad/speech", 60.0)

    workdir = Path(tempfile.mkdtemp(prefix="esiaf-bench-voiceid-"))
    placed = build_recording(files, workdir / "utterances.wav", 1.5)
    pipeline = VoicePipeline(workdir)
    try:
        arrived, _ = pipeline.play(workdir / "utterances.wav", fast=False, timeout_s=placed[-1].end_s + 120)
    finally:
        pipeline.close()
    hangover_ns = int(SegmenterParams().keep_alive_ms * 1_000_000)
    latencies = [(t - f["anchor"]["span"]["end_ns"] - hangover_ns) / 1e6 for t, f in arrived]
    return {"pipeline_results": len(latencies), "latency_p50_ms": statistics.median(latencies) if latencies else -1.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--pipeline", action="store_true", help="also measure latency through the pipeline")
    parser.add_argument("--variants", action="store_true", help="also evaluate the variants of VARIANTS (a table)")
    parser.add_argument("--room-enrolment", action="store_true",
                        help="also room trials against clean enrolment, with and without reverberant copies")
    args = parser.parse_args()
    data = load_emodb()
    names, speakers, neutral, clips = (list(column) for column in zip(*data, strict=True))
    encoder = VoiceEncoder()
    speech_s = sum(c.size for c in clips) / 16000
    started = time.process_time()
    clean = np.stack([encoder.embed(c) for c in clips])
    figures: dict[str, float | int] = {"utterances": len(clips), "speech_s": speech_s,
                                       "cpu_s_per_speech_s": (time.process_time() - started) / speech_s}
    figures.update(evaluate(names, speakers, neutral, clean))
    show(figures)
    calm = [i for i, n in enumerate(neutral) if n]  # neutral speech only: enrolment and trials alike
    show({f"neutral_{k}": v for k, v in evaluate([names[i] for i in calm], [speakers[i] for i in calm],
                                                 [True] * len(calm), clean[calm]).items()})
    room_clips = through_room(clips)
    room = np.stack([encoder.embed(c) for c in room_clips])
    show({f"room_{k}": v for k, v in evaluate(names, speakers, neutral, room).items()})
    show({f"room_neutral_{k}": v for k, v in evaluate([names[i] for i in calm], [speakers[i] for i in calm],
                                                      [True] * len(calm), room[calm]).items()})
    if args.room_enrolment:
        clean_enrolment_in_room(encoder, names, speakers, neutral, clips, clean, room)
    if args.variants:
        compare_variants(encoder, names, speakers, neutral, {"clean": clips, "room": room_clips},
                         {("clean", "dense"): clean, ("room", "dense"): room})  # the default: VoiceEncoder.embed
    if args.pipeline:
        wavs = SHARED_DATA / "emodb" / "wav"
        show(pipeline_latency([wavs / n for n in names[::60]]))


# name: (embedding, scoring, extra copies of each enrolment utterance: (perturbation, its parameter))
SPEED = (("speed", 0.9), ("speed", 1.1))
TILT = (("tilt", 0.7), ("tilt", -0.7))
VARIANTS = {
    "baseline (the default until now): 1.6 s partials at 1.3/s (resemblyzer's), top-3 cosine":
        ("partials", "cosine", ()),
    "whole utterance: one LSTM pass": ("whole", "cosine", ()),
    "dense partials: 2.5/s (step 0.4 s, 75 % overlap): the default now": ("dense", "cosine", ()),
    "cosine after subtracting the cohort's mean embedding": ("partials", "centred", ()),
    "adaptive s-norm, cohort top 20": ("partials", "snorm", ()),
    "enrolment + speed-perturbed copies (×0.9, ×1.1)": ("partials", "cosine", SPEED),
    "enrolment + tilted copies (pre-emphasis 0.7, low-pass 0.7)": ("partials", "cosine", TILT),
    "enrolment + speed and tilted copies": ("partials", "cosine", SPEED + TILT),
    "adaptive s-norm + speed-perturbed enrolment": ("partials", "snorm", SPEED),
    "adaptive s-norm + tilted enrolment": ("partials", "snorm", TILT),
}
EMBEDDERS = {"partials": lambda encoder, clip: encoder.embed(clip, partials_per_s=RESEMBLYZER_PARTIALS_PER_S),
             "whole": lambda encoder, clip: encoder.embed(clip, whole=True),
             "dense": lambda encoder, clip: encoder.embed(clip, partials_per_s=2.5)}
COHORT_TOP = 20
COHORT_SENTENCES = 10  # RoboCup questions read by each flite voice


def compare_variants(encoder: VoiceEncoder, names: list[str], speakers: list[str], neutral: list[bool],
                     conditions: dict[str, list[np.ndarray]], cache: dict[tuple[str, str], np.ndarray]) -> None:
    """One row per variant: closed-set accuracy and open-set EER (threshold), all emotions and
    neutral only, clean and in the room. The cohort (esiaf_services/voiceid/cohort.py: real non-EmoDB
    speech of the shared data + flite voices) goes through the same condition as the trials."""
    from esiaf_services.voiceid.augment import speed_perturbed, tilted
    from esiaf_services.voiceid.cohort import flite_clips, real_clips, robocup_questions
    sentences = robocup_questions(SHARED_DATA, COHORT_SENTENCES)
    cohort_clips = [c for _, c in real_clips(SHARED_DATA) + flite_clips(sentences)]
    cohort_audio = {"clean": cohort_clips, "room": through_room(cohort_clips)}
    print(f"cohort: {len(cohort_clips)} clips", flush=True)
    enrolled = sorted(i for idx in enrolment(speakers, neutral).values() for i in idx)
    calm = [i for i, n in enumerate(neutral) if n]

    def embeddings(condition: str, mode: str) -> np.ndarray:
        if (condition, mode) not in cache:
            cache[condition, mode] = np.stack([EMBEDDERS[mode](encoder, c) for c in conditions[condition]])
        return cache[condition, mode]

    cohorts: dict[tuple[str, str], np.ndarray] = {}
    copies: dict[tuple[str, str, str, float], dict[int, np.ndarray]] = {}
    print("| variant | closed, all | EER, all (threshold) | closed, neutral | EER, neutral (threshold) | "
          "room closed, all | room EER, all | room closed, neutral | room EER, neutral |")
    print("|---|---|---|---|---|---|---|---|---|")
    perturb = {"speed": speed_perturbed, "tilt": tilted}
    for name, (mode, scoring, perturbations) in VARIANTS.items():
        cells = []
        for condition in conditions:
            everything = embeddings(condition, mode)
            if (condition, mode) not in cohorts:
                cohorts[condition, mode] = np.stack([EMBEDDERS[mode](encoder, c) for c in cohort_audio[condition]])
            cohort = cohorts[condition, mode]
            extra = None
            for kind, value in perturbations:
                if (condition, mode, kind, value) not in copies:
                    copies[condition, mode, kind, value] = {i: EMBEDDERS[mode](encoder, perturb[kind](
                        conditions[condition][i], value)) for i in enrolled}
            if perturbations:
                extra = {i: np.stack([copies[condition, mode, kind, value][i] for kind, value in perturbations])
                         for i in enrolled}
            book: Callable[[dict[str, np.ndarray]], VoiceBook] = VoiceBook
            if scoring == "centred":
                mean = cohort.mean(axis=0)
                everything = _unit(everything - mean)
                extra = extra and {i: _unit(e - mean) for i, e in extra.items()}
            elif scoring == "snorm":
                def book(voices, cohort=cohort):
                    return VoiceBook(voices, cohort=cohort, cohort_top=COHORT_TOP)
            whole = evaluate(names, speakers, neutral, everything, book, extra)
            position = {i: n for n, i in enumerate(calm)}
            calm_extra = extra and {position[i]: e for i, e in extra.items() if i in position}
            only = evaluate([names[i] for i in calm], [speakers[i] for i in calm], [True] * len(calm),
                            everything[calm], book, calm_extra)
            for figures in (whole, only):
                cells.append(f"{100 * figures['closed_accuracy']:.1f} %")
                cells.append(f"{100 * figures['open_eer']:.1f} % ({figures['open_eer_threshold']:.2f})"
                             if condition == "clean" else f"{100 * figures['open_eer']:.1f} %")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


# reverberant noisy copies of clean enrolment utterances: rooms unlike the test room (RT60 0.4 s,
# 6×5×3 m, 1.5 m, kitchen noise at 10 dB): (RT60 s, room m, distance m, pink noise SNR dB)
ROOM_COPIES = ((0.3, (4.0, 5.0, 2.8), 1.0, 20.0), (0.6, (7.0, 6.0, 3.0), 2.0, 5.0))


def clean_enrolment_in_room(encoder: VoiceEncoder, names: list[str], speakers: list[str], neutral: list[bool],
                            clips: list[np.ndarray], clean: np.ndarray, room: np.ndarray) -> None:
    """Room trials against a clean enrolment (as a WAV enrolment would be), without and with
    reverberant noisy copies of each enrolment utterance (esiaf_services/voiceid/augment.py)."""
    from esiaf_services.voiceid.augment import reverberant
    enrolled = sorted(i for idx in enrolment(speakers, neutral).values() for i in idx)
    copies = {i: np.stack([encoder.embed(reverberant(clips[i], *copy, seed=n)) for n, copy in enumerate(ROOM_COPIES)])
              for i in enrolled}
    calm = [i for i, n in enumerate(neutral) if n]
    position = {i: n for n, i in enumerate(calm)}
    print("| room trials | closed, all | EER, all (threshold) | closed, neutral | EER, neutral (threshold) |")
    print("|---|---|---|---|---|")
    for name, enrol_from, extra in (("room enrolment (the room rows above)", None, None),
                                    ("clean enrolment", clean, None),
                                    ("clean enrolment + 2 reverberant noisy copies", clean, copies)):
        cells = []
        whole = evaluate(names, speakers, neutral, room, extra=extra, enrol_from=enrol_from)
        only = evaluate([names[i] for i in calm], [speakers[i] for i in calm], [True] * len(calm), room[calm],
                        extra=extra and {position[i]: e for i, e in extra.items() if i in position},
                        enrol_from=None if enrol_from is None else enrol_from[calm])
        for figures in (whole, only):
            cells.append(f"{100 * figures['closed_accuracy']:.1f} %")
            cells.append(f"{100 * figures['open_eer']:.1f} % ({figures['open_eer_threshold']:.2f})")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def show(figures: dict[str, float | int]) -> None:
    for name, value in figures.items():
        print(f"{name}={value:.4f}" if isinstance(value, float) else f"{name}={value}", flush=True)


if __name__ == "__main__":
    main()

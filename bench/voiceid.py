"""Voiceid: speaker identification on EmoDB, clean and through a simulated room; CPU and latency.

Every EmoDB utterance (10 speakers, 535, acted emotions) is cut to its speech span
(``esiaf.scenes.speech_bounds``, as a VAD segment would be) and embedded by each encoder of
``--models`` (ge2e, dvector, fused: esiaf/speech/speaker/encoders.py); every figure below is
given per encoder, side by side in a closing table.

- thresholds: each encoder's is calibrated on voices that are not EmoDB's (CMU ARCTIC's two
  speakers, flite's four voices reading RoboCup questions: ``calibration_clips``), the open-set
  EER point there (the middle of the gap where they separate); the EmoDB false rejections and
  acceptances at it are reported, never a threshold fitted on EmoDB;
- two strangers: two unenrolled speakers alternating (``two_strangers``), clean and in the room: they
  must get two different anonymous ids and never an enrolled name;
- ``--mean-weight W``: every figure under that scoring (``scoring.VoiceBook``; default the voiceid's),
  its thresholds calibrated under it too;
- ``--learning``: closed set, each speaker's utterances in file order after the 3-utterance
  neutral enrolment, learning as it goes (``scoring.LearningRule``, ``--learn-margin``): accuracy
  over the last half of each speaker's utterances, with and without learning;
- ``--denoise``: a third condition, the room's utterances (enrolment, trials and calibration alike)
  through the denoiser service's filter (DeepFilterNet 3, esiaf_services/denoiser/filter.py);
- ``--every N``: a subset (every Nth file, and every enrolment utterance); ``--no-room``;
  ``--cache DIR``: embeddings kept between runs;

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
  the test room (``ROOM_COPIES``, ``MORE_COPIES``), per encoder (ge2e, dvector);
- with ``--quality``, the voiceid's quality gate (esiaf/speech/speaker/quality.py ``problem``: an
  utterance whose estimated SNR is under ``quality_min_snr_db`` or whose speech span is under
  ``quality_min_speech_s`` is ``unknown``, never a name): each voice enrolled from its 3 clean
  utterances and their 2 room copies (as a WAV enrolment is), every other utterance identified
  at the voiceid's default threshold, clean and in the room, without the gate and with it at several
  SNRs: right names, wrong names, unknown; and the quality estimates of EmoDB and of the calibration
  voices (ARCTIC, flite), clean and in the room;
- ``latency_p50_ms``: with ``--pipeline``, a few utterances played in real time through
  grabber → vad → voiceid → orchestrator: arrival of the fused result minus (end of the segment's
  speech + the VAD's hang-over), as bench/emotion.py.

    python bench/voiceid.py [--models ge2e,dvector,fused] [--every N] [--no-room] [--learning] [--mean-weight W]
                            [--cache DIR] [--pipeline] [--variants] [--room-enrolment] [--quality]
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
from esiaf.speech.speaker.encoders import MODELS, Encoder  # noqa: E402
from esiaf.speech.speaker.ge2e import RESEMBLYZER_PARTIALS_PER_S, VoiceEncoder  # noqa: E402
from esiaf.tools.testing import SHARED_DATA  # noqa: E402
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


def through_room(utterances: list[np.ndarray], snrs_db: tuple[float, ...] = (SNR_DB,)) -> list[np.ndarray]:
    """Each utterance through the test room, the kitchen noise ``snrs_db[n % len(snrs_db)]`` under the n-th."""
    import pyroomacoustics as pra
    from scipy.signal import fftconvolve  # np.convolve's result to rounding, and 100× faster on the noise
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
    noise = fftconvolve(noise if noise.ndim == 1 else noise[:, 0], noise_rir)
    rng = np.random.default_rng(0)
    out = []
    for n, samples in enumerate(utterances):
        speech = fftconvolve(samples, speech_rir)[:samples.size + 1600]
        start = rng.integers(0, noise.size - speech.size)
        clip = noise[start:start + speech.size]
        gain = np.sqrt(np.mean(speech ** 2) / np.mean(clip ** 2) / 10 ** (snrs_db[n % len(snrs_db)] / 10))
        out.append((speech + gain * clip).astype(np.float32))
    return out


def audio_conditions(clips: list[np.ndarray], no_room: bool, denoise: bool) -> dict[str, list[np.ndarray]]:
    """The clips as tried: clean, through the room (unless ``no_room``), and the room's denoised."""
    conditions = {"clean": clips}
    if not no_room:
        conditions["room"] = through_room(clips)
        if denoise:
            conditions["room-denoised"] = denoised(conditions["room"])
    return conditions


def denoised(utterances: list[np.ndarray]) -> list[np.ndarray]:
    """Each utterance through the denoiser service's filter, flushed at its end, one after the other (as
    the service denoises the vad's utterances of a stream)."""
    from esiaf_services.denoiser.filter import ChannelFilter
    f = ChannelFilter(16000)
    return [np.concatenate([f.process(u[i:i + 320]) for i in range(0, u.size, 320)] + [f.flush()])
            for u in utterances]


def eer(genuine: np.ndarray, impostor: np.ndarray) -> tuple[float, float]:
    """Equal error rate and the threshold where false rejections = false acceptances; where a range of
    thresholds is as close (trials that separate perfectly: every threshold between the highest
    impostor and the lowest genuine score), the middle of that range."""
    best, rate, closest = 1.0, 0.5, []
    for threshold in np.unique(np.concatenate([genuine, impostor])):
        false_reject, false_accept = np.mean(genuine < threshold), np.mean(impostor >= threshold)
        gap = abs(false_reject - false_accept)
        if gap < best - 1e-12:
            best, rate, closest = gap, (false_reject + false_accept) / 2, [threshold]
        elif abs(gap - best) <= 1e-12:
            closest.append(threshold)
    if best == 0.0 and rate == 0.0:  # separated: the last tied threshold is the lowest genuine score
        below = impostor[impostor < closest[0]]
        return 0.0, float((closest[-1] + (below.max() if below.size else closest[0])) / 2)
    return float(rate), float((closest[0] + closest[-1]) / 2)


def enrolment(speakers: list[str], neutral: list[bool]) -> dict[str, list[int]]:
    """Speaker → indices of its enrolment utterances: the first ENROL_UTTERANCES neutral ones."""
    return {s: [i for i, (sp, n) in enumerate(zip(speakers, neutral, strict=True)) if sp == s and n][:ENROL_UTTERANCES]
            for s in sorted(set(speakers))}


def evaluate(names: list[str], speakers: list[str], neutral: list[bool], embeddings: np.ndarray,
             book: Callable[[dict[str, np.ndarray]], VoiceBook] = VoiceBook,
             extra: dict[int, np.ndarray] | None = None, enrol_from: np.ndarray | None = None,
             threshold: float | None = None) -> dict[str, float]:
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
    rate, at = eer(np.array(genuine), np.array(impostor))
    figures = {"closed_accuracy": float(np.mean(correct)), "closed_trials": len(trials),
               "open_eer": rate, "open_eer_threshold": at,
               "open_genuine_trials": len(genuine), "open_impostor_trials": len(impostor)}
    if threshold is not None:  # calibrated elsewhere: the error rates there
        figures["calibrated_false_reject"] = float(np.mean(np.array(genuine) < threshold))
        figures["calibrated_false_accept"] = float(np.mean(np.array(impostor) >= threshold))
    return figures


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
    parser.add_argument("--models", default=",".join(MODELS), help="encoders compared (default: all three)")
    parser.add_argument("--every", type=int, default=1, help="a subset: every Nth EmoDB file (default 1: all)")
    parser.add_argument("--no-room", action="store_true", help="leave out the room rows")
    parser.add_argument("--learning", action="store_true", help="also learning as it goes, in file order")
    parser.add_argument("--learn-margin", type=float, default=LEARN_MARGIN, help="the learning rule's margin")
    parser.add_argument("--mean-weight", type=float, default=None,
                        help="the scoring's mean_weight for every figure (default: the voiceid's, VoiceIdSettings)")
    parser.add_argument("--cache", help="a folder keeping the embeddings (and their CPU time) between runs")
    parser.add_argument("--pipeline", action="store_true", help="also measure latency through the pipeline")
    parser.add_argument("--variants", action="store_true", help="also evaluate the variants of VARIANTS (a table)")
    parser.add_argument("--room-enrolment", action="store_true",
                        help="also room trials against clean enrolment, with and without reverberant copies")
    parser.add_argument("--denoise", action="store_true", help="also the room's utterances denoised by the "
                        "denoiser service's filter (DeepFilterNet 3), enrolled and tried so: a condition of its own")
    parser.add_argument("--quality", action="store_true",
                        help="also the voiceid's quality gate: names right and wrong with and without it")
    args = parser.parse_args()
    models = args.models.split(",")
    if args.no_room and (args.variants or args.room_enrolment or args.quality):
        parser.error("--variants, --room-enrolment and --quality need the room (leave out --no-room)")
    if not set(models) <= set(MODELS):
        parser.error(f"--models: some of {', '.join(MODELS)}")
    data = load_emodb()
    first_neutral = enrolment([d[1] for d in data], [d[2] for d in data])  # the subset keeps every enrolment
    keep = sorted({i for idx in first_neutral.values() for i in idx} | set(range(0, len(data), args.every)))
    data = [data[i] for i in keep]
    names, speakers, neutral, clips = (list(column) for column in zip(*data, strict=True))
    speech_s = sum(c.size for c in clips) / 16000
    print(f"EmoDB: {len(clips)} utterances ({speech_s:.0f} s of speech), every {args.every}. file "
          "and every speaker's first 3 neutral ones", flush=True)
    calibration = calibration_clips()
    print(f"calibration: {len(calibration)} clips of {len(set(s for s, _ in calibration))} speakers "
          "(ARCTIC, flite), none of them EmoDB's", flush=True)
    conditions = audio_conditions(clips, args.no_room, args.denoise)
    cal_conditions = audio_conditions([c for _, c in calibration], args.no_room, args.denoise)
    cache = Path(args.cache) if args.cache else None
    embedded = {condition: embed_all(models, audio, cache, f"emodb-{args.every}-{condition}")
                for condition, audio in conditions.items()}
    cal_embedded = {condition: embed_all(models, audio, cache, f"calibration-{condition}")
                    for condition, audio in cal_conditions.items()}
    rows: dict[str, dict[str, float]] = {}
    from esiaf_services.voiceid.service import VoiceIdSettings
    weight = VoiceIdSettings.model_fields["mean_weight"].default if args.mean_weight is None else args.mean_weight
    print(f"scoring: mean_weight {weight:g}", flush=True)
    cal_speakers = [s for s, _ in calibration]
    for model in models:
        row = rows[model] = {"cpu_s_per_speech_s": embedded["clean"][1][model] / speech_s}
        for condition in conditions:
            row.update(condition_figures(condition, names, speakers, neutral, embedded[condition][0][model],
                                         (cal_speakers, cal_embedded[condition][0][model]), weight))
        if args.learning:
            row.update(learning(speakers, neutral, embedded["clean"][0][model],
                                row["clean_calibrated_threshold"], args.learn_margin, weight))
            row.update(learning_open(speakers, neutral, embedded["clean"][0][model],
                                     row["clean_calibrated_threshold"], args.learn_margin, weight))
        print(f"[{model}]", flush=True)
        show(row)
        if args.learning:
            compare_scorings(model, speakers, neutral, embedded["clean"][0][model],
                             (cal_speakers, cal_embedded["clean"][0][model]), args.learn_margin)
    print_table(rows, list(conditions), args.learning)
    if args.room_enrolment:
        room_enrolments(models, names, speakers, neutral, clips, {c: e[0] for c, e in embedded.items()}, weight)
    if args.quality:
        quality_gates(models, speakers, neutral, clips, weight, calibration)
    if args.variants:
        encoder = VoiceEncoder()
        clean, room = embedded["clean"][0]["ge2e"], embedded.get("room", embedded["clean"])[0]["ge2e"]
        compare_variants(encoder, names, speakers, neutral, {"clean": clips, "room": conditions["room"]},
                         {("clean", "dense"): clean, ("room", "dense"): room})  # the default: VoiceEncoder.embed
    if args.pipeline:
        wavs = SHARED_DATA / "emodb" / "wav"
        show(pipeline_latency([wavs / n for n in names[::60]]))


def condition_figures(condition: str, names: list[str], speakers: list[str], neutral: list[bool],
                      everything: np.ndarray, calibration: tuple[list[str], np.ndarray],
                      weight: float) -> dict[str, float]:
    """One encoder's figures in one condition under the scoring ``weight`` (``VoiceBook``'s mean_weight):
    its threshold calibrated on the calibration voices, closed and open set over all utterances and
    the neutral ones, two strangers."""
    def book(voices: dict[str, np.ndarray]) -> VoiceBook:
        return VoiceBook(voices, mean_weight=weight)

    calm = [i for i, n in enumerate(neutral) if n]
    threshold, cal_eer = calibrate(*calibration, weight)
    row = {f"{condition}_calibrated_threshold": threshold, f"{condition}_calibration_eer": cal_eer}
    for subset, figures in (("all", evaluate(names, speakers, neutral, everything, book, threshold=threshold)),
                            ("neutral", evaluate([names[i] for i in calm], [speakers[i] for i in calm],
                                                 [True] * len(calm), everything[calm], book, threshold=threshold))):
        row.update({f"{condition}_{subset}_{k}": v for k, v in figures.items()})
    row.update({f"{condition}_{k}": v for k, v in two_strangers(speakers, neutral, everything, threshold,
                                                                 weight).items()})
    return row


def embed_all(models: list[str], clips: list[np.ndarray], cache: Path | None = None,
              key: str = "") -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Each model's (n, size) embeddings of the clips and the CPU seconds they took (fused: both parts');
    with ``cache``, kept there as ``{key}-{model}.npz`` and read back by a later run."""
    from esiaf.speech.speaker.encoders import fuse, shared_encoder
    out: dict[str, np.ndarray] = {}
    cpu: dict[str, float] = {}
    for model in ("ge2e", "dvector"):
        if model in models or "fused" in models:
            kept = cache / f"{key}-{model}-{len(clips)}.npz" if cache else None
            if kept and kept.is_file():
                with np.load(kept) as stored:
                    out[model], cpu[model] = stored["embeddings"], float(stored["cpu_s"])
                continue
            encoder = shared_encoder(model)
            started = time.process_time()
            out[model] = np.stack([encoder.embed(c) for c in clips])
            cpu[model] = time.process_time() - started
            if kept:
                kept.parent.mkdir(parents=True, exist_ok=True)
                np.savez(kept, embeddings=out[model], cpu_s=cpu[model])
    if "fused" in models:
        out["fused"] = np.stack([fuse(a, b) for a, b in zip(out["ge2e"], out["dvector"], strict=True)])
        cpu["fused"] = cpu["ge2e"] + cpu["dvector"]
    return out, cpu


CALIBRATION_SENTENCES = 12  # RoboCup questions read by each flite voice


def calibration_clips() -> list[tuple[str, np.ndarray]]:
    """(speaker, speech span) of voices that are not EmoDB's: CMU ARCTIC's two speakers and flite's
    four voices reading RoboCup questions: the thresholds are set on them, never on the trials."""
    from esiaf_services.voiceid.cohort import flite_clips, real_clips, robocup_questions
    out = []
    for name, clip in real_clips(SHARED_DATA):
        for speaker in ("aew", "axb"):
            if f"_{speaker}_" in name:
                out.append((speaker, clip))
    for name, clip in flite_clips(robocup_questions(SHARED_DATA, CALIBRATION_SENTENCES)):
        out.append((name.rsplit("-", 1)[0], clip))
    return out


def calibrate(speakers: list[str], embeddings: np.ndarray, mean_weight: float = 0.0) -> tuple[float, float]:
    """The open-set EER threshold (and EER) on the calibration voices: each speaker enrolled from its
    first ENROL_UTTERANCES clips; genuine trials its other clips against its voice, impostor trials
    each speaker's clips' best score over the others' voices (that speaker left out). Where genuine
    and impostor trials separate (EER 0, as the clean ones do), the middle of the gap (eer)."""
    ids = sorted(set(speakers))
    enrol = {s: [i for i, sp in enumerate(speakers) if sp == s][:ENROL_UTTERANCES] for s in ids}
    voices = {s: embeddings[idx] for s, idx in enrol.items()}
    enrolled = {i for idx in enrol.values() for i in idx}
    genuine, impostor = [], []
    for i, speaker in enumerate(speakers):
        if i in enrolled:
            continue
        scores = VoiceBook(voices, mean_weight=mean_weight).scores(embeddings[i])
        genuine.append(scores[speaker])
        impostor.append(max(v for s, v in scores.items() if s != speaker))
    rate, threshold = eer(np.array(genuine), np.array(impostor))
    return threshold, rate


LEARN_MARGIN = 0.05  # cosine over the next voice (set beforehand, not fitted on EmoDB)
LEARNT_PER_VOICE = 50


def learning(speakers: list[str], neutral: list[bool], embeddings: np.ndarray, threshold: float,
             margin: float = 0.05, mean_weight: float = 0.0, only: set[str] | None = None) -> dict[str, float]:
    """Closed set, each voice enrolled from 3 neutral utterances, then every other utterance in file order,
    identified; one the voice wins by ``margin`` over the next and over the threshold is added to it as
    learnt (at most LEARNT_PER_VOICE, the oldest dropped). Scoring: ``VoiceBook``'s with ``mean_weight``
    (0: top-3 over every embedding). ``only``: a closed set of those speakers alone (their utterances,
    their voices). Accuracy over the last half of each speaker's trials, with and without learning, and
    how many were learnt and how many of those wrongly."""
    from esiaf_services.voiceid.scoring import LearningRule
    keep = [i for i, s in enumerate(speakers) if only is None or s in only]
    speakers, neutral, embeddings = [speakers[i] for i in keep], [neutral[i] for i in keep], embeddings[keep]
    enrol = enrolment(speakers, neutral)
    enrolled = {i for idx in enrol.values() for i in idx}
    trials = [i for i in range(len(speakers)) if i not in enrolled]
    last_half = set()
    for speaker in enrol:
        own = [i for i in trials if speakers[i] == speaker]
        last_half.update(own[len(own) // 2:])
    rule = LearningRule(threshold=threshold, margin=margin)
    voices = {s: embeddings[idx] for s, idx in enrol.items()}
    fixed = VoiceBook(voices, mean_weight=mean_weight)
    learnt: dict[str, list[np.ndarray]] = {s: [] for s in enrol}
    right_fixed, right_learning, added, wrong_added = [], [], 0, 0
    for i in trials:
        book = VoiceBook(voices, learnt={s: np.stack(e) for s, e in learnt.items() if e}, mean_weight=mean_weight)
        scores = book.scores(embeddings[i])
        best = max(scores, key=scores.__getitem__)
        if i in last_half:
            right_learning.append(best == speakers[i])
            fixed_scores = fixed.scores(embeddings[i])
            right_fixed.append(max(fixed_scores, key=fixed_scores.__getitem__) == speakers[i])
        if rule.learns(scores):
            learnt[best].append(embeddings[i])
            if len(learnt[best]) > LEARNT_PER_VOICE:  # the oldest learnt goes, never an enrolled one
                del learnt[best][0]
            added += 1
            wrong_added += best != speakers[i]
    return {"learning_last_half_accuracy": float(np.mean(right_learning)),
            "fixed_last_half_accuracy": float(np.mean(right_fixed)), "learning_trials": len(right_learning),
            "learnt": added, "learnt_wrongly": wrong_added}


def learning_open(speakers: list[str], neutral: list[bool], embeddings: np.ndarray, threshold: float,
                  margin: float = 0.05, mean_weight: float = 0.0) -> dict[str, float]:
    """Learning with strangers about: the open set's 3 rotations (7 enrolled from 3 neutral utterances,
    3 unknown), every other utterance in file order, learning as it goes. How many were learnt, how
    many of them from a stranger or into the wrong voice, and the strangers' utterances accepted as an
    enrolled voice (at ``threshold``) with and without learning."""
    from esiaf_services.voiceid.scoring import LearningRule
    ids = sorted(set(speakers))
    enrol = enrolment(speakers, neutral)
    enrolled = {i for idx in enrol.values() for i in idx}
    rule = LearningRule(threshold=threshold, margin=margin)
    added = wrong = accepted = accepted_fixed = strangers = 0
    for rotation in range(3):
        unknown = set(ids[rotation * UNKNOWN_SPEAKERS:(rotation + 1) * UNKNOWN_SPEAKERS])
        voices = {s: embeddings[idx] for s, idx in enrol.items() if s not in unknown}
        fixed = VoiceBook(voices, mean_weight=mean_weight)
        learnt: dict[str, list[np.ndarray]] = {s: [] for s in voices}
        for i in (i for i in range(len(speakers)) if i not in enrolled):
            book = VoiceBook(voices, learnt={s: np.stack(e) for s, e in learnt.items() if e}, mean_weight=mean_weight)
            scores = book.scores(embeddings[i])
            best = max(scores, key=scores.__getitem__)
            if speakers[i] in unknown:
                strangers += 1
                accepted += scores[best] >= threshold
                accepted_fixed += max(fixed.scores(embeddings[i]).values()) >= threshold
            if rule.learns(scores):
                learnt[best].append(embeddings[i])
                del learnt[best][:-LEARNT_PER_VOICE]
                added += 1
                wrong += best != speakers[i]
    return {"open_learnt": added, "open_learnt_wrongly": wrong, "open_stranger_trials": strangers,
            "open_strangers_accepted_learning": accepted / strangers,
            "open_strangers_accepted_fixed": accepted_fixed / strangers}


MEAN_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the scorings compared; 0: top-3 over every embedding


def compare_scorings(model: str, speakers: list[str], neutral: list[bool], embeddings: np.ndarray,
                     calibration: tuple[list[str], np.ndarray], margin: float) -> None:
    """Learning as it goes under each scoring of MEAN_WEIGHTS, each with its threshold calibrated on the
    calibration voices; chosen honestly: the weight best on one half of EmoDB's speakers (a closed set
    of those 5) is reported on the other half (a closed set of the other 5), both ways."""
    ids = sorted(set(speakers))
    halves = (set(ids[:len(ids) // 2]), set(ids[len(ids) // 2:]))
    print(f"[{model}] scorings, learning in file order (margin {margin}); halves "
          f"A={','.join(sorted(halves[0]))} B={','.join(sorted(halves[1]))}")
    print("| scoring | threshold | all 10: fixed | all 10: learning (learnt / wrong) | A: fixed | A: learning | "
          "B: fixed | B: learning |")
    print("|---|---|---|---|---|---|---|---|")
    results: dict[float, list[dict[str, float]]] = {}
    for weight in MEAN_WEIGHTS:
        threshold, _ = calibrate(*calibration, mean_weight=weight)
        results[weight] = [learning(speakers, neutral, embeddings, threshold, margin, weight, only)
                           for only in (None, *halves)]
        cells = [f"{weight:g}", f"{threshold:.3f}"]
        for n, figures in enumerate(results[weight]):
            cells.append(f"{100 * figures['fixed_last_half_accuracy']:.1f} %")
            cells.append(f"{100 * figures['learning_last_half_accuracy']:.1f} %"
                         + (f" ({figures['learnt']:.0f} / {figures['learnt_wrongly']:.0f})" if n == 0 else ""))
        print("| " + " | ".join(cells) + " |", flush=True)
    for chosen_on, reported_on in ((1, 2), (2, 1)):
        best = max(MEAN_WEIGHTS, key=lambda w: results[w][chosen_on]["learning_last_half_accuracy"])
        held_out = results[best][reported_on]
        print(f"chosen on {'AB'[chosen_on - 1]}: mean_weight {best:g}; on {'AB'[reported_on - 1]}: learning "
              f"{100 * held_out['learning_last_half_accuracy']:.1f} % against top-3 learning "
              f"{100 * results[0.0][reported_on]['learning_last_half_accuracy']:.1f} % and top-3 fixed "
              f"{100 * results[0.0][reported_on]['fixed_last_half_accuracy']:.1f} %", flush=True)


STRANGER_UTTERANCES = 10  # each of the two strangers', alternating: 20 in all
ANONYMOUS_BELOW = 0.03  # the anonymous threshold under the voice threshold, as encoders.ANONYMOUS_THRESHOLDS


def two_strangers(speakers: list[str], neutral: list[bool], embeddings: np.ndarray, threshold: float,
                  mean_weight: float = 0.0) -> dict[str, float]:
    """Two unenrolled speakers alternating, STRANGER_UTTERANCES each (their first in file order, any
    emotion), against the 7 enrolled voices of the open set's rotations: every pair of the 3 unknown
    speakers of each rotation (9 pairs). Each utterance is identified at ``threshold``; unknown, it goes
    to ``scoring.AnonymousVoices`` (``threshold - ANONYMOUS_BELOW``), as in the service. Per pair: how many
    were named as an enrolled voice (never right), how many anonymous ids, how many utterances were
    misassigned (named, or not their speaker's most frequent id, or that id shared with the other
    speaker: the fewer of the two then count), and whether the pair got 2 stable ids (2 ids, ≤ 1
    misassigned)."""
    from itertools import combinations

    from esiaf_services.voiceid.scoring import AnonymousVoices
    ids = sorted(set(speakers))
    enrol = enrolment(speakers, neutral)
    enrolled = {i for idx in enrol.values() for i in idx}
    pairs, named, id_counts, misassigned, stable = 0, 0, [], [], 0
    for rotation in range(3):
        unknown = ids[rotation * UNKNOWN_SPEAKERS:(rotation + 1) * UNKNOWN_SPEAKERS]
        book = VoiceBook({s: embeddings[idx] for s, idx in enrol.items() if s not in unknown},
                         mean_weight=mean_weight)
        for a, b in combinations(unknown, 2):
            own = {s: [i for i, sp in enumerate(speakers) if sp == s and i not in enrolled][:STRANGER_UTTERANCES]
                   for s in (a, b)}
            voices = AnonymousVoices(threshold - ANONYMOUS_BELOW)
            given: dict[str, list[str]] = {a: [], b: []}
            turns = min(len(own[a]), len(own[b]))  # a subset (--every) may have fewer
            for i, j in zip(own[a][:turns], own[b][:turns], strict=True):
                for speaker, index in ((a, i), (b, j)):
                    match = book.identify(embeddings[index], threshold)
                    given[speaker].append(match.label or voices.assign(embeddings[index])[0])
            pairs += 1
            named_here = sum(label in enrol for labels in given.values() for label in labels)
            main = {s: max(set(labels), key=labels.count) for s, labels in given.items()}
            wrong = sum(label != main[s] for s, labels in given.items() for label in labels)
            if main[a] == main[b]:  # one id for both: the speaker with fewer of it is misassigned
                wrong += min(given[a].count(main[a]), given[b].count(main[b]))
            anonymous_ids = {label for labels in given.values() for label in labels if label not in enrol}
            named += named_here
            id_counts.append(len(anonymous_ids))
            misassigned.append(wrong)
            stable += len(anonymous_ids) == 2 and main[a] != main[b] and wrong <= 1
    return {"strangers_pairs": pairs, "strangers_named": named, "strangers_ids_mean": float(np.mean(id_counts)),
            "strangers_misassigned_mean": float(np.mean(misassigned)), "strangers_stable_pairs": stable}


def print_table(rows: dict[str, dict[str, float]], conditions: list[str], learnt: bool) -> None:
    """The models side by side, one line per measure (docs/benchmarks.md's table)."""
    measures = []
    for condition in conditions:
        measures += [(f"{condition}: closed set, neutral", f"{condition}_neutral_closed_accuracy", "%"),
                     (f"{condition}: closed set, all", f"{condition}_all_closed_accuracy", "%"),
                     (f"{condition}: open-set EER, neutral", f"{condition}_neutral_open_eer", "%"),
                     (f"{condition}: open-set EER, all", f"{condition}_all_open_eer", "%"),
                     (f"{condition}: threshold calibrated on ARCTIC + flite (their EER)",
                      f"{condition}_calibrated_threshold", "t"),
                     (f"{condition}: at it, all: false rejections / false acceptances",
                      f"{condition}_all_calibrated", "fr")]
    for condition in conditions:
        measures.append((f"{condition}: two strangers alternating, 10 utterances each (9 pairs): stable pairs "
                         "(2 ids, ≤ 1 misassigned) / ids per pair / misassigned per pair / named", condition, "s"))
    if learnt:
        measures += [("clean, closed, file order, last half: fixed enrolment", "fixed_last_half_accuracy", "%"),
                     ("same, learning as it goes (learnt / of them wrong)", "learning_last_half_accuracy", "l"),
                     ("clean, open set in file order: strangers accepted, fixed enrolment",
                      "open_strangers_accepted_fixed", "%"),
                     ("same, learning as it goes (learnt / of them wrong or a stranger's)",
                      "open_strangers_accepted_learning", "o")]
    measures.append(("CPU s per s of speech", "cpu_s_per_speech_s", "f"))
    print("| measure | " + " | ".join(rows) + " |")
    print("|---|" + "---|" * len(rows))
    for label, key, kind in measures:
        cells = []
        for row in rows.values():
            if kind == "%":
                cells.append(f"{100 * row[key]:.1f} %")
            elif kind == "t":
                rate = row[key.replace("calibrated_threshold", "calibration_eer")]
                cells.append(f"{row[key]:.3f} ({100 * rate:.1f} %)")
            elif kind == "fr":
                cells.append(f"{100 * row[key + '_false_reject']:.1f} % / {100 * row[key + '_false_accept']:.1f} %")
            elif kind == "s":
                cells.append(f"{row[key + '_strangers_stable_pairs']:.0f} / {row[key + '_strangers_ids_mean']:.1f} / "
                             f"{row[key + '_strangers_misassigned_mean']:.1f} / {row[key + '_strangers_named']:.0f}")
            elif kind == "o":
                cells.append(f"{100 * row[key]:.1f} % ({row['open_learnt']:.0f} / {row['open_learnt_wrongly']:.0f})")
            elif kind == "l":
                cells.append(f"{100 * row[key]:.1f} % ({row['learnt']:.0f} / {row['learnt_wrongly']:.0f})")
            else:
                cells.append(f"{row[key]:.4f}")
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


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
    from esiaf.speech.speaker.augment import speed_perturbed, tilted
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


# reverberant noisy copies of clean enrolment utterances (esiaf/speech/speaker/augment.py ROOMS): rooms
# unlike the test room (RT60 0.4 s, 6×5×3 m, 1.5 m, kitchen noise at 10 dB), pink noise; the WAV
# enrolment's default is the first 2
ROOM_COPIES = 2
MORE_COPIES = 4


def room_enrolments(models: list[str], names: list[str], speakers: list[str], neutral: list[bool],
                    clips: list[np.ndarray], embedded: dict[str, dict[str, np.ndarray]], weight: float) -> None:
    """clean_enrolment_in_room for each model but fused (``embedded``: condition → model → embeddings)."""
    from esiaf.speech.speaker.encoders import shared_encoder
    for model in (m for m in models if m != "fused"):
        print(f"[{model}] room trials, enrolment clean or in the room (mean_weight {weight:g})", flush=True)
        clean_enrolment_in_room(shared_encoder(model), names, speakers, neutral, clips, embedded["clean"][model],
                                embedded["room"][model], lambda voices: VoiceBook(voices, mean_weight=weight))


def clean_enrolment_in_room(encoder: Encoder, names: list[str], speakers: list[str], neutral: list[bool],
                            clips: list[np.ndarray], clean: np.ndarray, room: np.ndarray,
                            book: Callable[[dict[str, np.ndarray]], VoiceBook] = VoiceBook) -> None:
    """Room trials against a clean enrolment (as a WAV enrolment would be), without and with
    reverberant noisy copies of each enrolment utterance (esiaf/speech/speaker/augment.py room_copies, as
    the orchestrator's WAV enrolment makes them): the first ROOM_COPIES, MORE_COPIES (multi-condition
    enrolment)."""
    from esiaf.speech.speaker.augment import room_copies
    enrolled = sorted(i for idx in enrolment(speakers, neutral).values() for i in idx)
    more = {i: np.stack([encoder.embed(copy) for copy in room_copies(clips[i], MORE_COPIES)]) for i in enrolled}
    copies = {i: e[:ROOM_COPIES] for i, e in more.items()}
    calm = [i for i, n in enumerate(neutral) if n]
    position = {i: n for n, i in enumerate(calm)}
    print("| room trials | closed, all | EER, all (threshold) | closed, neutral | EER, neutral (threshold) |")
    print("|---|---|---|---|---|")
    for name, enrol_from, extra in (("room enrolment (the room rows above)", None, None),
                                    ("clean enrolment", clean, None),
                                    ("clean enrolment + 2 reverberant noisy copies", clean, copies),
                                    ("clean enrolment + 4 reverberant noisy copies (20, 10, 5, 0 dB)", clean, more)):
        cells = []
        whole = evaluate(names, speakers, neutral, room, book, extra=extra, enrol_from=enrol_from)
        only = evaluate([names[i] for i in calm], [speakers[i] for i in calm], [True] * len(calm), room[calm], book,
                        extra=extra and {position[i]: e for i, e in extra.items() if i in position},
                        enrol_from=None if enrol_from is None else enrol_from[calm])
        for figures in (whole, only):
            cells.append(f"{100 * figures['closed_accuracy']:.1f} %")
            cells.append(f"{100 * figures['open_eer']:.1f} % ({figures['open_eer_threshold']:.2f})")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    from esiaf.speech.speaker.encoders import threshold
    at = threshold(encoder.name, book({}).mean_weight)
    print(f"| clean trials | closed, all | EER, all (threshold) | closed, neutral | EER, neutral (threshold) | "
          f"names at the voiceid's threshold {at:g}, right / wrong: all | neutral |")
    print("|---|---|---|---|---|---|---|")
    enrol = enrolment(speakers, neutral)
    trials = [i for i in range(len(names)) if i not in enrolled]
    for name, extra in (("clean enrolment", None), ("clean enrolment + 2 reverberant noisy copies", copies),
                        ("clean enrolment + 4 reverberant noisy copies", more)):
        cells = []
        whole = evaluate(names, speakers, neutral, clean, book, extra=extra)
        only = evaluate([names[i] for i in calm], [speakers[i] for i in calm], [True] * len(calm), clean[calm], book,
                        extra=extra and {position[i]: e for i, e in extra.items() if i in position})
        for figures in (whole, only):
            cells.append(f"{100 * figures['closed_accuracy']:.1f} %")
            cells.append(f"{100 * figures['open_eer']:.1f} % ({figures['open_eer_threshold']:.2f})")
        voices = book({s: np.concatenate([clean[idx]] + ([extra[i] for i in idx] if extra else []))
                       for s, idx in enrol.items()})
        for subset in (trials, [i for i in trials if neutral[i]]):
            given = [voices.identify(clean[i], at).label for i in subset]
            right = sum(g == speakers[i] for g, i in zip(given, subset, strict=True))
            wrong = sum(bool(g) and g != speakers[i] for g, i in zip(given, subset, strict=True))
            cells.append(f"{100 * right / len(subset):.1f} / {100 * wrong / len(subset):.1f} %")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


QUALITY_SNRS_DB = (-30.0, 0.0, 3.0, 5.0, 8.0, 10.0, 12.0, 15.0)  # the gate's SNRs compared (-30: the span alone)
QUALITY_SPEECH_S = (0.0, 0.3, 0.5, 0.8)  # ... and its shortest speech spans
MIXED_SNRS_DB = (0.0, 5.0, 10.0, 15.0, 20.0)  # the room with the n-th utterance's noise at the (n % 5)-th
# the gate is calibrated for the most right names less WRONG_NAME_COST × the wrong ones: a robot that greets the
# wrong person by name is worse than one that greets nobody; the table shows cost 1 too
WRONG_NAME_COST = 2


def quality_gates(models: list[str], speakers: list[str], neutral: list[bool], clips: list[np.ndarray],
                  weight: float, calibration: list[tuple[str, np.ndarray]]) -> None:
    """quality_gate for each model but fused, at the voiceid's default threshold for ``weight``."""
    from esiaf.speech.speaker.encoders import shared_encoder, threshold
    for model in (m for m in models if m != "fused"):
        quality_gate(shared_encoder(model), speakers, neutral, clips, threshold(model, weight), weight, calibration)


def quality_gate(encoder: Encoder, speakers: list[str], neutral: list[bool], clips: list[np.ndarray],
                 threshold: float, weight: float, calibration: list[tuple[str, np.ndarray]]) -> None:
    """The voiceid's quality gate (quality.voice_problem) at each SNR of QUALITY_SNRS_DB and speech span of
    QUALITY_SPEECH_S. Each voice is enrolled from its 3 clean utterances and their ROOM_COPIES room copies
    (as a WAV enrolment is); every other utterance is identified, clean, in the room at 10 dB and in the
    room at MIXED_SNRS_DB. Calibrated on the calibration voices (ARCTIC, flite: the same trials, each
    speaker from its first 3 clips): the gate that gives most right names less WRONG_NAME_COST × the
    wrong ones (and, shown beside it, 1 ×), the loosest of equals; the first gate (-30 dB, 0 s) is none.
    On EmoDB: closed-set accuracy (a gated trial counts as wrong), and at the voiceid's threshold names
    right / wrong / unknown (of them for quality)."""
    from esiaf.speech.speaker.augment import room_copies
    from esiaf.speech.speaker.quality import measure, voice_problem
    from esiaf_services.voiceid.service import VoiceIdSettings
    default_speech = VoiceIdSettings.model_fields["quality_min_speech_s"].default
    default_snr = VoiceIdSettings.model_fields["quality_min_snr_db"].default
    gates = [(snr, speech) for snr in QUALITY_SNRS_DB for speech in QUALITY_SPEECH_S]

    Trials = tuple[list[int], list, list]  # trial indices, their matches, their qualities

    def trials_of(who: list[str], audio: list[np.ndarray], enrol: dict[str, list[int]]) -> dict[str, Trials]:
        """Per condition: (trial indices, matches, qualities)."""
        enrolled = {i for idx in enrol.values() for i in idx}
        copies = {i: [encoder.embed(c) for c in room_copies(audio[i], ROOM_COPIES)] for i in enrolled}
        embedded = {i: encoder.embed(audio[i]) for i in enrolled}
        book = VoiceBook({s: np.stack([embedded[i] for i in idx] + [e for i in idx for e in copies[i]])
                          for s, idx in enrol.items()}, mean_weight=weight)
        trials = [i for i in range(len(who)) if i not in enrolled]
        out = {}
        said = [audio[i] for i in trials]
        for cond, heard in (("clean", said), ("room 10 dB", through_room(said)),
                            ("room 0-20 dB", through_room(said, MIXED_SNRS_DB))):
            out[cond] = (trials, [book.identify(encoder.embed(c), threshold) for c in heard],
                         [measure(c) for c in heard])
        return out

    def tally(who: list[str], run: Trials, gate: tuple[float, float]) -> tuple[int, int, int, int, int]:
        """Closed-set right, names right, names wrong, gated, trials."""
        trials, matches, qualities = run
        gated = [voice_problem(q, *gate) is not None for q in qualities]
        best = [max(m.scores, key=m.scores.__getitem__) for m in matches]
        closed = sum(not g and b == who[i] for g, b, i in zip(gated, best, trials, strict=True))
        given = ["" if g else m.label for g, m in zip(gated, matches, strict=True)]
        right = sum(g == who[i] for g, i in zip(given, trials, strict=True))
        wrong = sum(bool(g) and g != who[i] for g, i in zip(given, trials, strict=True))
        return closed, right, wrong, sum(gated), len(trials)

    cal_who = [s for s, _ in calibration]
    cal_enrol = {s: [i for i, w in enumerate(cal_who) if w == s][:ENROL_UTTERANCES] for s in sorted(set(cal_who))}
    cal = trials_of(cal_who, [c for _, c in calibration], cal_enrol)
    def names(gate: tuple[float, float]) -> tuple[int, int]:  # the calibration's right and wrong names
        counts = [tally(cal_who, cal[c], gate)[1:3] for c in cal]
        return sum(r for r, _ in counts), sum(w for _, w in counts)

    chosen = {}
    for cost in (1, WRONG_NAME_COST):
        def worth(gate: tuple[float, float], cost: int = cost) -> tuple[float, float, float]:
            right, wrong = names(gate)
            return right - cost * wrong, -gate[0], -gate[1]  # equals: the loosest
        chosen[cost] = max(gates, key=worth)
        print(f"[{encoder.name}] quality gate calibrated on ARCTIC + flite ({sum(len(t[0]) for t in cal.values())} "
              f"trials, clean, room 10 dB, room 0-20 dB), a wrong name costing {cost} right one(s): "
              f"SNR ≥ {chosen[cost][0]:g} dB, speech ≥ {chosen[cost][1]:g} s (the voiceid's default: "
              f"{default_snr:g} dB, {default_speech:g} s)", flush=True)
    emodb = trials_of(speakers, clips, enrolment(speakers, neutral))
    print("| gate: SNR, speech span | calibration: right / wrong names | " + " | ".join(
        f"{c}: closed set | {c}: right / wrong / unknown (gated)" for c in emodb) + " |")
    print("|---|---|" + "---|---|" * len(emodb))
    for gate in gates:
        cells = ["{} / {}".format(*names(gate))]
        for cond in emodb:
            closed, right, wrong, gated, n = tally(speakers, emodb[cond], gate)
            cells.append(f"{100 * closed / n:.1f} %")
            cells.append(f"{100 * right / n:.1f} % / {100 * wrong / n:.1f} % / {100 * (n - right - wrong) / n:.1f} % "
                         f"({100 * gated / n:.1f} %)")
        label = f"≥ {gate[0]:g} dB, ≥ {gate[1]:g} s" + (" (none)" if gate == gates[0] else "") + (
            " (default)" if gate == (default_snr, default_speech) else "") + "".join(
            f" (best at cost {cost})" for cost, best in chosen.items() if gate == best)
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def show(figures: dict[str, float | int]) -> None:
    for name, value in figures.items():
        print(f"{name}={value:.4f}" if isinstance(value, float) else f"{name}={value}", flush=True)


if __name__ == "__main__":
    main()

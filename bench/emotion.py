"""Emotion and gender services: CPU per second of speech, memory, and latency from segment end to result.

EmoDB utterances (default: 30 of speakers 03 and 08, 1.5 s of silence between them) are played in
real time through grabber → vad → emotion + gender → orchestrator, with the bundled models
(``emotion4``, ``gender``), twice in one run: ``apart``, emotion and gender each in a process of
its own (``esiaf run --apart``; each computes the openSMILE features of every utterance), and
``hosted``, gender a guest in emotion's process (``esiaf run``'s default; the features computed
once per utterance). Beside it, in this process, the same utterances are classified by the same
backends with no transport, to show what the model itself costs. Figures, as ``name=value``:

- ``<mode>_cpu_s_per_speech_s_<service>``: CPU seconds (psutil, user + system) a service's process
  used while the file played, per second of speech played (the utterances' total duration), idle
  time included; ``<mode>_cpu_s_per_speech_s_emotion_gender``: both together (hosted: the one process);
- ``<mode>_rss_mb_<service>``: its resident memory after the file played;
- ``<mode>_latency_<kind>_p50_ms`` / ``p90`` / ``max``: arrival of the fused result at a websocket
  client minus (capture time of the end of the segment's speech + the VAD's 400 ms hang-over),
  i.e. from the moment a segmenter could know the utterance had ended;
- ``model_cpu_s_per_speech_s_features`` / ``_onnx_<model>``: openSMILE (once for both models) and
  each model's ONNX classifier alone, in this process;
- ``thesis_cpu_s_per_speech_s_<service>``: the thesis' realistic pipeline, 30,120 (emotion) and
  5,960 (gender) CPU seconds for 83 minutes of speech.

    python -m bench.emotion [--utterances 30] [--gap-s 1.5] [--modes apart,hosted] [--chunk-ms 20]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import soundfile

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from esiaf.speech.classifiers import load_backend  # noqa: E402
from esiaf.speech.segmenter import SegmenterParams  # noqa: E402
from esiaf.tools.testing import SHARED_DATA  # noqa: E402
from esiaf_services.emotion.service import MODELS as EMOTION_MODELS  # noqa: E402
from esiaf_services.emotion.tools.pipeline import EmotionPipeline, build_recording  # noqa: E402
from esiaf_services.gender.service import MODELS as GENDER_MODELS  # noqa: E402

HANGOVER_NS = int(SegmenterParams().keep_alive_ms * 1_000_000)
THESIS_SPEECH_S = 83 * 60
THESIS_CPU_S = {"emotion": 30_120, "gender": 5_960}
MODELS = {"emotion": "emotion4", "gender": "gender"}
MODEL_DIRS = {"emotion": EMOTION_MODELS, "gender": GENDER_MODELS}  # each service's bundled models


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    k = (len(ordered) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


def model_cost(files: list[Path], speech_s: float) -> dict[str, float]:
    """CPU seconds per second of speech, in this process, of the openSMILE features (computed once for
    both bundled models) and of each model's ONNX classifier over them."""
    samples = [soundfile.read(f, dtype="float32")[0] for f in files]
    classifiers = {model: load_backend("onnx", model, models_dir=MODEL_DIRS[kind]) for kind, model in MODELS.items()}
    extractor = next(iter(classifiers.values())).features.extractor  # type: ignore[attr-defined]
    started = time.process_time()
    vectors = [extractor(s) for s in samples]
    figures = {"model_cpu_s_per_speech_s_features": (time.process_time() - started) / speech_s}
    for model, classifier in classifiers.items():
        started = time.process_time()
        for vector in vectors:
            classifier._run(vector)  # type: ignore[attr-defined]
        figures[f"model_cpu_s_per_speech_s_onnx_{model}"] = (time.process_time() - started) / speech_s
    return figures


def play(workdir: Path, hosted: bool, audio_s: float, speech_s: float,
         chunk_ms: float | None = None) -> dict[str, float | int]:
    """One run of the pipeline over the recording: CPU, memory and latency figures."""
    mode = "hosted" if hosted else "apart"
    print(f"pipeline ({mode}): playing {speech_s:.0f} s of speech ({audio_s:.0f} s in all) in real time ...",
          file=sys.stderr, flush=True)
    folder = workdir / mode
    folder.mkdir()
    pipeline = EmotionPipeline(folder, MODELS["emotion"], MODELS["gender"], "bench", hosted=hosted)
    try:
        before = pipeline.cpu_s()
        arrived, _ = pipeline.play(workdir / "utterances.wav", fast=False, timeout_s=audio_s + 120, chunk_ms=chunk_ms)
        after = pipeline.cpu_s()
        rss = pipeline.rss_mb()
    finally:
        pipeline.close()
    figures: dict[str, float | int] = {}
    for kind in MODELS:
        latencies = [(t - f["anchor"]["span"]["end_ns"] - HANGOVER_NS) / 1e6 for t, f in arrived if f["fusion"] == kind]
        figures[f"{mode}_results_{kind}"] = len(latencies)
        if latencies:
            figures[f"{mode}_latency_{kind}_p50_ms"] = statistics.median(latencies)
            figures[f"{mode}_latency_{kind}_p90_ms"] = percentile(latencies, 0.9)
            figures[f"{mode}_latency_{kind}_max_ms"] = max(latencies)
    for name in sorted(after):
        figures[f"{mode}_cpu_s_per_speech_s_{name}"] = (after[name] - before.get(name, 0.0)) / speech_s
    figures[f"{mode}_cpu_s_per_speech_s_emotion_gender"] = sum(
        float(figures.get(f"{mode}_cpu_s_per_speech_s_{name}", 0.0)) for name in MODELS)
    for name in sorted(rss):
        figures[f"{mode}_rss_mb_{name}"] = rss[name]
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--utterances", type=int, default=30)
    parser.add_argument("--gap-s", type=float, default=1.5)
    parser.add_argument("--modes", default="apart,hosted", help="apart, hosted or both (in this order)")
    parser.add_argument("--chunk-ms", type=float, help="the grabber's chunk (default: its own, 50 ms)")
    args = parser.parse_args()
    emodb = SHARED_DATA / "emodb" / "wav"
    if not emodb.is_dir():
        raise SystemExit(f"bench: {emodb} is absent (the shared data folder belongs beside the repository)")
    files = sorted(p for p in emodb.glob("*.wav") if p.name[:2] in ("03", "08"))[::2][:args.utterances]
    workdir = Path(tempfile.mkdtemp(prefix="esiaf-bench-emotion-"))
    placed = build_recording(files, workdir / "utterances.wav", args.gap_s)
    speech_s = sum(u.end_s - u.start_s for u in placed)
    audio_s = soundfile.info(str(workdir / "utterances.wav")).duration

    figures: dict[str, float | int] = {"utterances": len(files), "speech_s": speech_s, "audio_s": audio_s}
    modes = args.modes.split(",")
    for mode in modes:
        figures.update(play(workdir, mode == "hosted", audio_s, speech_s, args.chunk_ms))
    if set(modes) == {"apart", "hosted"}:
        figures["hosted_over_apart_cpu"] = (float(figures["hosted_cpu_s_per_speech_s_emotion_gender"])
                                            / float(figures["apart_cpu_s_per_speech_s_emotion_gender"]))
    for kind, cpu_s in THESIS_CPU_S.items():
        figures[f"thesis_cpu_s_per_speech_s_{kind}"] = cpu_s / THESIS_SPEECH_S
    print("in-process: the same utterances through the backends alone ...", file=sys.stderr, flush=True)
    figures.update(model_cost(files, speech_s))
    for name, value in figures.items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}")


if __name__ == "__main__":
    main()

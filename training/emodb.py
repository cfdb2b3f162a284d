"""Trains and evaluates the bundled emotion and gender models on Berlin EmoDB.

    python -m training.emodb [--data ../shared/data/emodb] [--tasks emotion4,emotion7,gender]

For each task it extracts openSMILE ComParE 2016 functionals of every utterance's speech span,
as each way the vad service cuts would cut it (``features.VADS``, ``features.speech_span``: Silero
per window, the default; Silero per chunk; energy; cached in ``.cache/emotion/``, git-ignored),
trains on every span of each utterance, evaluates leave-one-speaker-out (train on 9 speakers, test
on each way's spans of the 10th, for each speaker), trains the final model on all 10 speakers and writes, in
``esiaf_services/emotion/models/``: ``<task>.onnx`` (standardisation + logistic regression, converted
with skl2onnx and checked against scikit-learn), ``<task>.json`` (label map and evaluation) and
``MODEL_CARD.md``. It also writes ``models/holdout/<task>.onnx``, trained without speakers 03 and
08, with its predictions for their utterances, for the end-to-end test. Needs ``.[emotion,train]``.
"""
from __future__ import annotations

import argparse
import csv
import json
import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import soundfile

from esiaf.speech.opensmile import (
    VADS,
    FeatureExtractor,
    speech_segments,
    speech_span,
    without_digital_silence,
)
from esiaf.tools.testing import SHARED_DATA
from esiaf_services.emotion.service import MODELS
from esiaf_services.gender.service import MODELS as GENDER_MODELS
from training.model_card import write_card

log = logging.getLogger("train")

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / ".cache" / "emotion"
FEATURE_SET = "ComParE_2016"
HOLDOUT_SPEAKERS = ("03", "08")  # one male, one female: the end-to-end test plays their utterances
EMOTIONS_4 = {"neutral": "neutral", "anger": "angry", "happiness": "happy", "sadness": "sad"}
EMOTIONS_7 = {**EMOTIONS_4, "boredom": "bored", "fear": "fearful", "disgust": "disgusted"}


@dataclass(frozen=True)
class Task:
    name: str
    column: str  # manifest column holding the class
    labels: dict[str, str]  # manifest value -> label the service reports
    regularisation_c: float  # logistic regression's C (inverse L2 strength); see MODEL_CARD.md for how chosen


TASKS = {t.name: t for t in (
    Task("emotion4", "emotion", EMOTIONS_4, 0.1),
    Task("emotion7", "emotion", EMOTIONS_7, 0.01),
    Task("gender", "gender", {"female": "female", "male": "male"}, 10.0),
)}


def read_manifest(data: Path) -> list[dict[str, str]]:
    with (data / "manifest.tsv").open() as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    missing = [r["path"] for r in rows if not (data / r["path"]).is_file()]
    if missing:
        raise SystemExit(f"train: {len(missing)} files of {data / 'manifest.tsv'} are missing, e.g. {missing[0]}")
    return rows


def features(data: Path, rows: list[dict[str, str]], vad: str) -> np.ndarray:
    """(utterances, features) of the speech spans the vad service's backend ``vad`` cuts, from the
    cache when it holds exactly these files."""
    import opensmile
    cache = CACHE / f"{FEATURE_SET}-spans-{vad}-opensmile{opensmile.__version__}.npz"
    paths = np.array([r["path"] for r in rows])
    if cache.is_file():
        stored = np.load(cache)
        if np.array_equal(stored["paths"], paths):
            return stored["features"]
    extractor = FeatureExtractor(FEATURE_SET)
    started = time.process_time()
    values = []
    for i, row in enumerate(rows):
        samples, rate = soundfile.read(data / row["path"], dtype="float32")
        if rate != extractor.sample_rate_hz:
            raise SystemExit(f"train: {row['path']} is {rate} Hz, expected {extractor.sample_rate_hz}")
        first, end = speech_span(samples, rate, vad=vad)  # what the VAD forwards as the segment's speech
        values.append(extractor(without_digital_silence(samples[first:end])))
        if (i + 1) % 100 == 0:
            log.info("features: %d/%d", i + 1, len(rows))
    speech_s = sum(float(r["duration_s"]) for r in rows)
    log.info("features: %s of %d files (%.0f s of speech, %s spans) in %.1f CPU s", FEATURE_SET, len(rows),
             speech_s, vad, time.process_time() - started)
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(cache, paths=paths, features=np.stack(values))
    return np.stack(values)


def longest_segments(data: Path, paths: list[str], vad: str) -> dict[str, np.ndarray]:
    """Per file, the features of the longest segment the vad service cutting as ``vad`` would cut of
    it: what the pipeline labels where its VAD splits an utterance at a pause (the end-to-end test's
    fused result overlapping the utterance most), where ``features`` takes all of its speech."""
    extractor = FeatureExtractor(FEATURE_SET)
    out = {}
    for path in paths:
        samples, rate = soundfile.read(data / path, dtype="float32")
        segments = speech_segments(samples, rate, vad=vad) or [(0, len(samples))]
        first, end = max(segments, key=lambda segment: segment[1] - segment[0])
        out[path] = extractor(without_digital_silence(samples[first:end]))
    return out


def make_model(task: Task):
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    return make_pipeline(StandardScaler(), LogisticRegression(C=task.regularisation_c, max_iter=5000))


def fit(task: Task, x: np.ndarray, y: np.ndarray):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=UserWarning)
        return make_model(task).fit(x, y)


def scores(truth: np.ndarray, predicted: np.ndarray, labels: list[str]) -> dict:
    from sklearn.metrics import accuracy_score, confusion_matrix, recall_score
    present = [label for label in labels if label in set(truth)]
    return {"uar": round(float(recall_score(truth, predicted, labels=present, average="macro")), 4),
            "accuracy": round(float(accuracy_score(truth, predicted)), 4), "utterances": len(truth),
            "confusion": confusion_matrix(truth, predicted, labels=labels).tolist()}


def leave_one_speaker_out(task: Task, x: dict[str, np.ndarray], y: np.ndarray, speakers: np.ndarray) -> dict:
    """Trained on the spans of every VAD of the other speakers, tested on each VAD's spans of the
    speaker left out: the figures for the default VAD (the first), and ``by_vad`` for each."""
    labels = sorted(set(y))
    predicted = {vad: np.empty(len(y), dtype=object) for vad in x}
    for speaker in sorted(set(speakers)):
        test = speakers == speaker
        model = fit(task, *both(x, y, ~test))
        for vad, values in x.items():
            predicted[vad][test] = model.predict(values[test])
        log.info("%s: fold without speaker %s done", task.name, speaker)
    by_vad = {vad: scores(y, p.astype(str), labels) for vad, p in predicted.items()}
    default = next(iter(x))
    result = {"labels": labels, "vad": default, **by_vad[default], "per_speaker": {},
              "by_vad": {vad: {k: v[k] for k in ("uar", "accuracy")} for vad, v in by_vad.items()}}
    for speaker in sorted(set(speakers)):
        mine = speakers == speaker
        per = scores(y[mine], predicted[default][mine].astype(str), labels)
        result["per_speaker"][speaker] = {k: per[k] for k in ("uar", "accuracy", "utterances")}
    return result


def both(x: dict[str, np.ndarray], y: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The training set: each utterance of ``rows`` once per VAD's span."""
    return np.concatenate([values[rows] for values in x.values()]), np.concatenate([y[rows]] * len(x))


def export(model, x: np.ndarray, path: Path) -> None:
    """ONNX of the fitted pipeline, checked against scikit-learn's own probabilities."""
    import onnxruntime
    from skl2onnx import to_onnx
    onnx_model = to_onnx(model, x[:1].astype(np.float32), options={"zipmap": False}, target_opset=17)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(onnx_model.SerializeToString())
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    ours = session.run(["probabilities"], {session.get_inputs()[0].name: x.astype(np.float32)})[0]
    difference = float(np.max(np.abs(ours - model.predict_proba(x))))
    if difference > 1e-3:
        raise SystemExit(f"train: {path} differs from scikit-learn by up to {difference:.4f} in probability")
    log.info("wrote %s (%d bytes; max probability difference to scikit-learn %.1e)", path,
             path.stat().st_size, difference)


def label_map(task: Task, model, **extra) -> dict:
    return {"task": task.name, "labels": [str(c) for c in model.classes_], "features": FEATURE_SET,
            "sample_rate_hz": 16000,
            "classifier": f"StandardScaler + LogisticRegression(C={task.regularisation_c}, L2)", **extra}


def train(task: Task, data: Path, rows: list[dict[str, str]], x_all: dict[str, np.ndarray],
          longest: dict[str, dict[str, np.ndarray]], out: Path, bundled: Path | None = None) -> dict:
    """``bundled``: where the model trained on everyone goes (``out`` if None); the held-out one goes
    to ``out``/holdout."""
    bundled = bundled or out
    keep = np.array([r[task.column] in task.labels for r in rows])
    x = {vad: values[keep] for vad, values in x_all.items()}
    y = np.array([task.labels.get(r[task.column], "") for r in rows])[keep]
    speakers = np.array([r["speaker"] for r in rows])[keep]
    paths = np.array([r["path"] for r in rows])[keep]
    evaluation = leave_one_speaker_out(task, x, y, speakers)
    log.info("%s LOSO: UAR %.3f accuracy %.3f (%s)", task.name, evaluation["uar"], evaluation["accuracy"],
             ", ".join(f"{vad} spans {v['accuracy']:.3f}" for vad, v in evaluation["by_vad"].items()))
    everyone = np.ones(len(y), dtype=bool)
    model = fit(task, *both(x, y, everyone))
    export(model, both(x, y, everyone)[0], bundled / f"{task.name}.onnx")
    card = label_map(task, model, data=str(data.name), loso=evaluation, trained_on={
        "utterances": len(y), "speakers": sorted(set(speakers)), "spans_of_vads": list(x)})
    (bundled / f"{task.name}.json").write_text(json.dumps(card, indent=1) + "\n")

    held = np.isin(speakers, HOLDOUT_SPEAKERS)
    holdout = fit(task, *both(x, y, ~held))
    export(holdout, both(x, y, ~held)[0], out / "holdout" / f"{task.name}.onnx")
    default = next(iter(x))  # the predictions are on the default VAD's spans; predicted_<vad> on the others'
    predicted = {vad: holdout.predict(values[held]).astype(str) for vad, values in x.items()}
    predicted.update({f"longest_{vad}": holdout.predict(np.stack([by_path[p] for p in paths[held]])).astype(str)
                      for vad, by_path in longest.items()})
    (out / "holdout" / f"{task.name}.json").write_text(json.dumps(label_map(
        task, holdout, trained_without_speakers=list(HOLDOUT_SPEAKERS), vad=default,
        held_out=scores(y[held], predicted[default], evaluation["labels"]),
        held_out_longest_segment=scores(y[held], predicted[f"longest_{default}"], evaluation["labels"]),
        predictions={p: {"truth": str(t), "predicted": str(predicted[default][i]),
                         **{f"predicted_{vad}": str(q[i]) for vad, q in predicted.items() if vad != default}}
                     for i, (p, t) in enumerate(zip(paths[held], y[held], strict=True))}),
        indent=1) + "\n")
    return card


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA / "emodb")
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--out", type=Path, default=None, help="every model here (default: each bundled model "
                        "in its service's models/, the held-out ones in esiaf_services/emotion/models/holdout)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    unknown = set(args.tasks.split(",")) - set(TASKS)
    if unknown:
        raise SystemExit(f"train: unknown task(s) {', '.join(sorted(unknown))}; known: {', '.join(TASKS)}")
    rows = read_manifest(args.data)
    x = {vad: features(args.data, rows, vad) for vad in VADS}  # the default VAD first
    held = [r["path"] for r in rows if r["speaker"] in HOLDOUT_SPEAKERS]
    longest = {vad: longest_segments(args.data, held, vad) for vad in VADS}
    for name in args.tasks.split(","):
        bundled = args.out or (GENDER_MODELS if name == "gender" else MODELS)
        train(TASKS[name], args.data, rows, x, longest, args.out or MODELS, bundled)
    write_card(args.out or MODELS, *([] if args.out else [GENDER_MODELS]))


if __name__ == "__main__":
    main()

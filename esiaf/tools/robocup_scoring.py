"""``esiaf eval robocup``'s scoring: each question matched to the fused result that overlaps it most,
recognised or not, its direction right or not, the points of the task, and the summary and table
printed at the end (the rules are in esiaf/tools/evaluation.py's docstring)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

WITHIN_DEG = 15.0
# the thesis' figures (Fig. 5.13: Pepper in a real hall, 6 runs), printed beside ours
THESIS = {"questions_recognised": 0.583, "mean_angle_error_deg": 68.3, "questions_recognised_2019_old": 0.467}


@dataclass
class Question:
    game: str  # riddle or bluff
    text: str
    azimuth_deg: float
    start_s: float
    end_s: float
    recognised: bool = False
    heard: str = ""  # the text of the fused result matched to it
    azimuth_error_deg: float | None = None  # None: no direction fused


@dataclass
class RunScore:
    name: str
    snr_db: float
    rt60_s: float
    questions: list[Question]
    spurious: int = 0
    fused: int = 0
    audio_s: float = 0.0
    pipeline_s: float = 0.0  # from the first audio to the end of stream, wall clock
    oracle_recognised: int = 0
    failed: bool = False  # the pipeline did not finish: every question counts as missed

    @property
    def points(self) -> int:
        return sum(10 * q.recognised + (10 if q.game == "bluff" and direction_right(q) else 0)
                   for q in self.questions)


def direction_right(question: Question) -> bool:
    return question.azimuth_error_deg is not None and question.azimuth_error_deg <= WITHIN_DEG


def normalise(text: str) -> str:
    import re
    return " ".join(re.sub(r"[^a-z0-9' ]+", " ", text.lower().replace("-", " ")).split())


def angle_difference_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def score(questions: list[Question], fused: list[dict[str, Any]]) -> int:
    """Matches fused results to questions (most overlap); fills each question in; returns the spurious count."""
    used: set[int] = set()
    for question in questions:
        overlaps = [(min(question.end_s, f["end_s"]) - max(question.start_s, f["start_s"]), i)
                    for i, f in enumerate(fused)]
        best = max((o for o in overlaps if o[0] > 0), default=None)
        if best is None:
            continue
        message = fused[best[1]]
        used.add(best[1])
        hypotheses = (message["anchor"].get("speech") or {}).get("hypotheses") or []
        question.heard = hypotheses[0]["text"] if hypotheses and not hypotheses[0].get("out_of_set") else ""
        question.recognised = normalise(question.heard) == normalise(question.text)
        ssl = (message.get("aggregates") or {}).get("ssl")
        if ssl:
            question.azimuth_error_deg = angle_difference_deg(ssl["azimuth_deg"], question.azimuth_deg)
    return sum(1 for i, f in enumerate(fused) if i not in used and not any(
        min(q.end_s, f["end_s"]) > max(q.start_s, f["start_s"]) for q in questions))


def oracle(signals: np.ndarray, questions: list[Question], rate: int, recogniser) -> int:
    """Questions recognised from their true segments (± 0.2 s) of the first microphone."""
    right = 0
    for question in questions:
        first, last = int(max(0.0, question.start_s - 0.2) * rate), int((question.end_s + 0.2) * rate)
        pcm = (np.clip(signals[first:last, 0], -1, 1) * 32767).astype("<i2").tobytes()
        hypotheses = recogniser.recognise(pcm)
        right += bool(hypotheses) and normalise(hypotheses[0].text) == normalise(question.text)
    return right


def summary(scores: list[RunScore], oracle_too: bool) -> dict[str, float]:
    questions = [q for run in scores for q in run.questions]
    errors = [q.azimuth_error_deg for q in questions if q.azimuth_error_deg is not None]
    figures = {
        "runs": len(scores),
        "questions": len(questions),
        "questions_recognised": sum(q.recognised for q in questions) / len(questions),
        "ssl_within_15": sum(direction_right(q) for q in questions) / len(questions),
        "ssl_reported": len(errors) / len(questions),
        "mean_angle_error_deg": float(np.mean(errors)) if errors else math.nan,
        "median_angle_error_deg": float(np.median(errors)) if errors else math.nan,
        "spurious_per_run": sum(run.spurious for run in scores) / len(scores),
        "points_per_run": sum(run.points for run in scores) / len(scores),
        "real_time_factor": (sum(run.pipeline_s for run in scores if not run.failed)
                             / (sum(run.audio_s for run in scores if not run.failed) or math.nan)),
        "failed_runs": sum(run.failed for run in scores),
    }
    if oracle_too:
        figures["oracle_questions_recognised"] = sum(run.oracle_recognised for run in scores) / len(questions)
    return figures


def table(scores: list[RunScore], figures: dict[str, float], oracle_too: bool) -> str:
    rows = [f"{'run':<18} {'SNR dB':>6} {'RT60':>5} {'questions':>9} {'directions':>10} {'mean err':>8} "
            f"{'spurious':>8} {'points':>6}" + (f" {'oracle':>6}" if oracle_too else "")]
    for run in scores:
        errors = [q.azimuth_error_deg for q in run.questions if q.azimuth_error_deg is not None]
        rows.append(f"{run.name:<18} {run.snr_db:>6.1f} {run.rt60_s:>5.2f} "
                    f"{sum(q.recognised for q in run.questions):>6}/10 "
                    f"{sum(direction_right(q) for q in run.questions):>7}/10 "
                    f"{(np.mean(errors) if errors else math.nan):>7.1f}° {run.spurious:>8} {run.points:>6}"
                    + (f" {run.oracle_recognised:>3}/10" if oracle_too else ""))
    rows.append(f"{'all':<18} {'':>6} {'':>5} {100 * figures['questions_recognised']:>8.1f}% "
                f"{100 * figures['ssl_within_15']:>9.1f}% {figures['mean_angle_error_deg']:>7.1f}° "
                f"{figures['spurious_per_run']:>8.2f} {figures['points_per_run']:>6.1f}"
                + (f" {100 * figures['oracle_questions_recognised']:>5.1f}%" if oracle_too else ""))
    rows.append(f"{'thesis (Pepper)':<18} {'':>6} {'':>5} {100 * THESIS['questions_recognised']:>8.1f}% "
                f"{'':>10} {THESIS['mean_angle_error_deg']:>7.1f}°")
    if oracle_too:
        rows.append(f"{'oracle':<18} {'':>6} {'':>5} {100 * figures['oracle_questions_recognised']:>8.1f}%   "
                    f"(true segments, one microphone, the same recogniser, no pipeline)")
    return "\n".join(rows)

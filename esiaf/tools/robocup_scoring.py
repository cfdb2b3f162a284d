"""``esiaf eval robocup``'s scoring: each question matched to the fused result that overlaps it most,
recognised or not, its direction right or not, the points of the task, and the summary and table
printed at the end (the rules are in esiaf/tools/evaluation.py's docstring)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
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
    commands: list[SpokenCommand] = field(default_factory=list)  # --task gpsr: said instead of questions

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


# the GPSR task (--task gpsr): commands, scored by their words and slots


@dataclass
class SpokenCommand:
    text: str
    slots: list[tuple[str, str]]  # (kind, value as spoken): name, location, object, category, gesture
    start_s: float
    end_s: float
    heard: str = ""  # the fused results overlapping it most, in order, their texts joined
    oracle: str = ""  # its true segment decoded without the pipeline

    @property
    def exact(self) -> bool:
        return normalise(self.heard) == normalise(self.text)


def word_errors(reference: str, hypothesis: str) -> int:
    """Substitutions, insertions and deletions turning ``hypothesis`` into ``reference`` (normalised words)."""
    ref, hyp = normalise(reference).split(), normalise(hypothesis).split()
    row = list(range(len(hyp) + 1))
    for i, word in enumerate(ref, 1):
        previous, row[0] = row[0], i
        for j, heard in enumerate(hyp, 1):
            previous, row[j] = row[j], min(row[j] + 1, row[j - 1] + 1, previous + (word != heard))
    return row[-1]


def slots_right(slots: list[tuple[str, str]], heard: str) -> int:
    """The slots whose words are in ``heard`` (as whole words, each occurrence counted once)."""
    words = f" {normalise(heard)} "
    right = 0
    for _kind, value in slots:
        phrase = f" {normalise(value)} "
        if phrase.strip() and phrase in words:
            right += 1
            words = words.replace(phrase, "  ", 1)
    return right


def score_commands(commands: list[SpokenCommand], fused: list[dict[str, Any]]) -> int:
    """Gives each fused result to the command it overlaps most; a command hears their texts, in order;
    returns the spurious count (fused results overlapping no command)."""
    spurious = 0
    for message in fused:
        overlaps = [(min(c.end_s, message["end_s"]) - max(c.start_s, message["start_s"]), i)
                    for i, c in enumerate(commands)]
        best = max((o for o in overlaps if o[0] > 0), default=None)
        if best is None:
            spurious += 1
            continue
        hypotheses = (message["anchor"].get("speech") or {}).get("hypotheses") or []
        text = hypotheses[0]["text"] if hypotheses and not hypotheses[0].get("out_of_set") else ""
        command = commands[best[1]]
        command.heard = f"{command.heard} {text}".strip()
    return spurious


def oracle_commands(signals: np.ndarray, commands: list[SpokenCommand], rate: int, recogniser) -> None:
    """Each command's true segment (± 0.2 s) of the first microphone decoded into its ``oracle``."""
    for command in commands:
        first, last = int(max(0.0, command.start_s - 0.2) * rate), int((command.end_s + 0.2) * rate)
        pcm = (np.clip(signals[first:last, 0], -1, 1) * 32767).astype("<i2").tobytes()
        hypotheses = recogniser.recognise(pcm)
        command.oracle = hypotheses[0].text if hypotheses else ""


def command_figures(commands: list[SpokenCommand], prefix: str = "", oracle_too: bool = False) -> dict[str, float]:
    """Commands exact, word error rate and slots right, over ``commands``."""
    figures: dict[str, float] = {}
    for name, heard in (("", [c.heard for c in commands]), ("oracle_", [c.oracle for c in commands])):
        if name and not oracle_too:
            continue
        words = sum(len(normalise(c.text).split()) for c in commands) or 1
        slots = sum(len(c.slots) for c in commands) or 1
        figures[f"{prefix}{name}commands_exact"] = sum(
            normalise(h) == normalise(c.text) for c, h in zip(commands, heard, strict=True)) / max(len(commands), 1)
        figures[f"{prefix}{name}word_error_rate"] = sum(
            word_errors(c.text, h) for c, h in zip(commands, heard, strict=True)) / words
        figures[f"{prefix}{name}slots_right"] = sum(
            slots_right(c.slots, h) for c, h in zip(commands, heard, strict=True)) / slots
    return figures


def gpsr_summary(scores: list[RunScore], oracle_too: bool) -> dict[str, float]:
    commands = [c for run in scores for c in run.commands]
    return {"runs": len(scores), "commands": len(commands),
            **command_figures(commands, oracle_too=oracle_too),
            "spurious_per_run": sum(run.spurious for run in scores) / len(scores),
            "real_time_factor": (sum(run.pipeline_s for run in scores if not run.failed)
                                 / (sum(run.audio_s for run in scores if not run.failed) or math.nan)),
            "failed_runs": sum(run.failed for run in scores)}


def gpsr_table(scores: list[RunScore], figures: dict[str, float], oracle_too: bool) -> str:
    rows = [f"{'run':<18} {'SNR dB':>6} {'RT60':>5} {'exact':>7} {'WER':>6} {'slots':>6} {'spurious':>8}"
            + (f" {'oracle':>6} {'WER':>6} {'slots':>6}" if oracle_too else "")]
    for run in scores:
        one = command_figures(run.commands, oracle_too=oracle_too)
        rows.append(f"{run.name:<18} {run.snr_db:>6.1f} {run.rt60_s:>5.2f} "
                    f"{sum(c.exact for c in run.commands):>4}/{len(run.commands):<2} "
                    f"{100 * one['word_error_rate']:>5.1f}% {100 * one['slots_right']:>5.1f}% {run.spurious:>8}"
                    + (f" {round(one['oracle_commands_exact'] * len(run.commands)):>3}/{len(run.commands):<2} "
                       f"{100 * one['oracle_word_error_rate']:>5.1f}% {100 * one['oracle_slots_right']:>5.1f}%"
                       if oracle_too else ""))
    rows.append(f"{'all':<18} {'':>6} {'':>5} {100 * figures['commands_exact']:>6.1f}% "
                f"{100 * figures['word_error_rate']:>5.1f}% {100 * figures['slots_right']:>5.1f}% "
                f"{figures['spurious_per_run']:>8.2f}"
                + (f" {100 * figures['oracle_commands_exact']:>5.1f}% {100 * figures['oracle_word_error_rate']:>5.1f}% "
                   f"{100 * figures['oracle_slots_right']:>5.1f}%" if oracle_too else ""))
    if oracle_too:
        rows.append("oracle: true segments, one microphone, the same recogniser, no pipeline")
    return "\n".join(rows)

"""``esiaf eval robocup``: the RoboCup@Home Speech & Person Recognition task, simulated, through the pipeline.

The thesis' second experiment (its Fig. 5.13) on rendered rooms instead of a convention hall. Each
run is a recording made with :mod:`esiaf.scenes`:

- a shoebox room (sides 6.5-9 m, RT60 drawn from 0.3-0.6 s) with the array (``--array``) near its
  centre, 1.2 m high, at a random heading;
- the riddle game: five questions from an operator in front of the robot (0° ± 10°);
- the blind man's bluff game: five questions, each from one of four people standing at about 0, 90,
  180 and 270° (± 10°);
- every talker 1-2 m away, four flite voices, questions drawn from the 50 RoboCup@Home 2018 questions;
- two loudspeakers in front of the robot (±20°, 2.5 m): babble (four voices saying the questions'
  answers at once) on one, kitchen noise (dish washing) on the other, together at an SNR drawn
  from ``--snr`` (each 3 dB quieter).

Each recording is played through the real pipeline (``esiaf run --fast --json`` with the options
given after ``--``) and scored against its truth:

- a question is **recognised** when the fused result overlapping it most has its exact sentence;
- its **direction** is right when that result's SSL aggregate is within 15° of the talker;
- a fused result overlapping no question is **spurious**;
- **points** as in the task: 10 per question recognised; in the blind man's bluff game 10 more per
  question whose direction is right (the robot turns to the right person).

A run whose pipeline fails (exits with an error, or does not finish in 10 minutes) is reported on
its own line and scored as answering nothing; ``failed_runs`` counts them.

The **oracle** row decodes each question's true segment of the first microphone with the same
recogniser and grammar, without the pipeline: what a perfect segmenter would give with one
microphone, so that a gain can be attributed to the front end.

``--task gpsr``: the General Purpose Service Robot task's commands instead of the questions, in the
same rooms (the same seed renders the same rooms, talkers, noise and SNR): ten commands a run drawn
from the GPSR grammar (``--category``, default 1) by :mod:`esiaf.tools.gpsr`. Pocketsphinx
recognises with that grammar as JSGF (``gpsr.gram`` in the work folder, and ``gpsr.dict``: the
project dictionary and flite's pronunciation of the words the bundled one lacks); Whisper
(``-- --asr whisper``) transcribes freely (the command language is too large for its closed set).
``--free`` runs pocketsphinx with its language model instead; ``--vocabulary`` gives the asr the GPSR
world's names, places, objects and categories as its ``vocabulary`` (``gpsr.vocabulary`` in the work
folder), and the oracle row the same.
Every fused result goes to the command it overlaps most, and a command hears their texts in order:

- a command is **exact** when what it heard is its text (normalised words);
- the **word error rate** is the edits (substitutions, insertions, deletions) over the commands' words;
- a **slot** (a name, location, object, category or gesture filled in by the grammar) is **right**
  when its words are in what the command heard.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from esiaf.tools.robocup_scoring import (
    Question,
    RunScore,
    SpokenCommand,
    direction_right,
    gpsr_summary,
    gpsr_table,
    normalise,
    oracle,
    oracle_commands,
    score,
    score_commands,
    summary,
    table,
)

REPO = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("ESIAF_SHARED_DATA") or REPO.parent / "shared" / "data")
VOICES = ("slt", "kal16", "awb", "rms")
KITCHEN = "noise/speech_commands_bg/doing_the_dishes.wav"
QUESTIONS = "robocup/questions.tsv"
GPSR_FOLDER = "robocup"
GPSR_COMMANDS_PER_RUN = 10
RUN_TIMEOUT_S = 600.0
DEFAULT_PIPELINE = ["--without", "emotion,gender,voiceid"]  # not scored: leave them out unless asked for


class EvalError(ValueError):
    """Options or material the harness cannot work with; the message says what to change."""


def read_questions_and_answers(data: Path) -> list[tuple[str, str]]:
    path = data / QUESTIONS
    rows = []
    for line in path.read_text(encoding="utf-8").splitlines():
        fields = line.split("\t")
        if line.startswith("#") or len(fields) < 3 or not fields[0].strip().isdigit():
            continue
        rows.append((fields[1].strip(), fields[2].strip()))
    if not rows:
        raise EvalError(f"{path} holds no questions (index<TAB>question<TAB>answer lines)")
    return rows


def babble_clip(rng: np.random.Generator, answers: list[str], out: Path, seconds: float = 40.0) -> Path:
    """Four flite voices saying answers at once, one after the other, to ``out`` (16 kHz WAV)."""
    import soundfile

    from esiaf.scenes import speak
    total = int(seconds * 16000)
    mix = np.zeros(total)
    for voice in VOICES:
        track, at = np.zeros(total), int(rng.uniform(0, 1.5) * 16000)
        while at < total:
            clip = speak(str(rng.choice(answers)), voice, 16000)
            clip = clip[:total - at]
            track[at:at + len(clip)] += clip / (np.sqrt(np.mean(clip ** 2)) + 1e-9)
            at += len(clip) + int(rng.uniform(0.1, 0.6) * 16000)
        mix += track
    soundfile.write(str(out), (0.5 * mix / np.max(np.abs(mix))).astype(np.float32), 16000)
    return out


def make_scene(index: int, seed: int, array: str, snr: tuple[float, float], data: Path, work: Path,
               questions: list[tuple[str, str]], texts: Sequence[str] | None = None):
    """The scene of run ``index``: (Scene, [(game, question)], snr_db); ``texts``: what the ten talkers
    say instead of questions (the room, talkers, noise and SNR stay those of the seed)."""
    from esiaf.scenes import NoiseSource, Scene, SpeechSource
    rng = np.random.default_rng([seed, index])
    room = (float(rng.uniform(6.5, 9.0)), float(rng.uniform(6.5, 9.0)), float(rng.uniform(2.7, 3.5)))
    centre = (room[0] / 2 + rng.uniform(-0.3, 0.3), room[1] / 2 + rng.uniform(-0.3, 0.3), 1.2)
    chosen = rng.choice(len(questions), size=10, replace=False)
    operator = str(rng.choice(VOICES))
    people = list(rng.permutation(VOICES))  # who stands at 0, 90, 180 and 270°
    speech, games, onset = [], [], 1.0 + rng.uniform(0, 1)
    for number, row in enumerate(chosen):
        text = questions[int(row)][0] if texts is None else texts[number]
        if number < 5:
            game, voice, azimuth = "riddle", operator, rng.uniform(-10, 10)
        else:
            place = int(rng.integers(4))
            game, voice, azimuth = "bluff", str(people[place]), 90.0 * place + rng.uniform(-10, 10)
        speech.append(SpeechSource(say=text, voice=voice, speaker=voice, azimuth_deg=float(azimuth % 360),
                                   distance_m=float(rng.uniform(1.0, 2.0)), onset_s=float(onset)))
        games.append(game)
        onset += 2.2 + 0.075 * len(text) + rng.uniform(1.5, 3.0)  # the question's length and a pause
    snr_db = float(rng.uniform(*snr))
    babble = work / f"babble-{seed}-{index}.wav"
    if not babble.exists():
        babble_clip(np.random.default_rng([seed, index, 1]), [answer for _, answer in questions], babble)
    noise = [NoiseSource(clip=str(babble), azimuth_deg=20.0, distance_m=2.5, snr_db=snr_db + 3.0),
             NoiseSource(clip=str(data / KITCHEN), azimuth_deg=340.0, distance_m=2.5, snr_db=snr_db + 3.0)]
    scene = Scene(array=array, room_m=room, rt60_s=float(rng.uniform(0.3, 0.6)), array_position_m=centre,
                  array_heading_deg=float(rng.uniform(0, 360)), speech=speech, noise=noise, tail_s=1.5,
                  seed=int(rng.integers(1 << 30)))
    return scene, games, snr_db


ROBOT_DELAY_S = 0.1  # from what the player publishes to its echo: a sound card's output buffer


def robot_speaks(scene, questions: list[tuple[str, str]], run_dir: Path) -> Path:
    """Adds the robot's loudspeaker to ``scene``: it answers each question with a flite sentence long enough
    to run into the next question, 7 cm in front of and below the array's centre, its echo 10 dB above the
    talkers and ROBOT_DELAY_S later than the reference; returns the reference (robot.wav), on the scene's
    timeline, for ``esiaf run --playback`` (with its transcript, robot.json, beside it)."""
    import soundfile

    from esiaf.scenes import NoiseSource, speak
    answers = dict(questions)
    fs = scene.sample_rate_hz
    clips = [speak(source.say, source.voice, fs) for source in scene.speech]
    total = round((max(s.onset_s + len(c) / fs for s, c in zip(scene.speech, clips, strict=True)) + scene.tail_s)
                  * fs)
    robot = np.zeros(total)
    transcript = []
    for source, clip in zip(scene.speech, clips, strict=True):
        at = round((source.onset_s + 0.3) * fs) + len(clip)
        text = (f"The answer to your question is: {answers.get(source.say, 'I do not know')}. "
                f"Do you have another question for me?")
        said = speak(text, "kal16", fs)[:max(0, total - at)]
        robot[at:at + len(said)] = said
        if len(said):
            transcript.append({"start_s": at / fs, "text": text})
    (run_dir / "robot.json").write_text(json.dumps(transcript))  # what it says: esiaf run --playback reads it
    reference = run_dir / "robot.wav"
    soundfile.write(str(reference), (0.5 * robot / max(np.max(np.abs(robot)), 1e-9)).astype(np.float32), fs)
    delay = round(ROBOT_DELAY_S * fs)
    echo = run_dir / "robot-echo.wav"
    soundfile.write(str(echo), np.concatenate([np.zeros(delay), robot])[:total].astype(np.float32), fs)
    scene.noise.append(NoiseSource(clip=str(echo), azimuth_deg=0.0, distance_m=0.07, elevation_deg=-45.0,
                                   snr_db=-10.0))
    return reference


def run_pipeline(audio: Path, array: str, options: list[str], work: Path, port: int, name: str,
                 grammar: str | None = "robocup", env: dict[str, str] | None = None) -> tuple[list, float]:
    """Plays ``audio`` through ``esiaf run --fast --json`` (with ``--grammar grammar`` unless None, and
    ``env`` added to its environment); the fused results (latest revision of each, ordered by start)
    with times relative to the stream's start, and the pipeline's wall time."""
    stream = f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"  # a workdir used again keeps its database: a new stream
    cmd = [sys.executable, "-m", "esiaf", "run", "--input", str(audio), "--array", array, "--fast", "--json",
           *(["--grammar", grammar] if grammar else []), "--workdir", str(work), "--port", str(port),
           "--stream-id", stream, *options]
    started = time.monotonic()
    with open(work / "launcher.log", "w") as log:
        try:
            done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=log, text=True, timeout=RUN_TIMEOUT_S,
                                  cwd=REPO, env={**os.environ, **(env or {}), "PYTHONPATH": str(REPO)})
        except subprocess.TimeoutExpired:
            raise EvalError(f"{name}: the pipeline did not finish within {RUN_TIMEOUT_S:g} s "
                            f"(see {work / 'launcher.log'})") from None
    if done.returncode != 0:
        tail = (work / "launcher.log").read_text().strip().splitlines()[-3:]
        raise EvalError(f"{name}: esiaf run exited with {done.returncode}: {' / '.join(tail)}")
    origin: int | None = None
    fused: dict[int, dict[str, Any]] = {}
    for line in done.stdout.splitlines():
        message = json.loads(line)
        if message.get("type") == "stream_start":
            origin = message["start_ns"]
        elif message.get("type") == "fused_withdrawn":  # the robot's own voice after all
            fused.pop(message["id"], None)
        elif message.get("type") == "fused_result" and (
                message["id"] not in fused or message["revision"] >= fused[message["id"]]["revision"]):
            fused[message["id"]] = message
    if origin is None:
        raise EvalError(f"{name}: esiaf run printed no stream start")
    results = sorted(fused.values(), key=lambda m: m["anchor"]["span"]["start_ns"])
    for message in results:
        span = message["anchor"]["span"]
        message["start_s"], message["end_s"] = (span["start_ns"] - origin) / 1e9, (span["end_ns"] - origin) / 1e9
    return results, time.monotonic() - started


class ClosedSetOracle:
    """Whisper's closed-set decoding (the asr's default for a closed set) behind the interface of
    ``PocketsphinxRecognizer.recognise``: the chosen question, or no hypothesis when out of set."""

    def __init__(self, scoring: str) -> None:
        from esiaf_services.asr.closed_set import ClosedSetDecoder
        from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
        from esiaf_services.asr.matching import SentenceMatcher
        from esiaf_services.asr.whisper import WhisperRecognizer
        self.matcher = SentenceMatcher.from_file(ROBOCUP_GRAMMAR, 0.6)
        self.whisper = WhisperRecognizer(n_best=10)
        self.prompt = ", ".join(self.matcher.vocabulary()) + "."
        self.decoder = ClosedSetDecoder(self.whisper.model, self.matcher) if scoring == "acoustic" else None

    def recognise(self, pcm: bytes) -> list:
        from esiaf_services.asr.matching import chosen_first
        from esiaf_services.asr.recognizer import Hypothesis
        samples = np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0
        if self.decoder is not None:
            result = self.decoder.decode(samples)
            return [Hypothesis(result.ranked[0].sentence, 1.0, ())] if result is not None and result.in_set else []
        hypotheses = self.whisper.recognise(samples, 16000, self.prompt).hypotheses
        matches = [self.matcher.match(h.text) for h in hypotheses]
        if not any(m.in_set for m in matches):
            return []
        return [Hypothesis(matches[chosen_first(matches)[0]].sentence, 1.0, ())]


class FreeWhisper:
    """Whisper's free transcription behind the interface of ``PocketsphinxRecognizer.recognise``,
    prompted with the vocabulary's ``entries`` as the asr prompts it."""

    def __init__(self, entries: list[str] | None = None) -> None:
        from esiaf_services.asr.vocabulary import prompt
        from esiaf_services.asr.whisper import WhisperRecognizer
        self.whisper = WhisperRecognizer()
        self.prompt = prompt(entries, self.whisper.model.hf_tokenizer)[0] if entries else None

    def recognise(self, pcm: bytes) -> list:
        samples = np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0
        return self.whisper.recognise(samples, 16000, self.prompt).hypotheses


def backend_of(pipeline: list[str]) -> str:
    """The recogniser the pipeline runs: ``--asr``, else ``ESIAF_ASR_BACKEND``, else pocketsphinx."""
    return pipeline[pipeline.index("--asr") + 1] if "--asr" in pipeline[:-1] else \
        os.environ.get("ESIAF_ASR_BACKEND", "pocketsphinx")


def gpsr_language(grammar, work: Path) -> tuple[Path, Path]:
    """The GPSR command language for pocketsphinx: ``work/gpsr.gram`` (JSGF) and ``work/gpsr.dict`` (the
    project dictionary and, for each word the bundled dictionary lacks, flite's pronunciation)."""
    from esiaf_services.asr.lexicon import BUNDLED_DICT, PROJECT_DICT, format_dictionary, read_dictionary
    from esiaf_services.asr.tools.make_robocup_grammar import PronunciationError, make_pronunciations
    gram, dictionary = work / "gpsr.gram", work / "gpsr.dict"
    gram.write_text(grammar.jsgf(), encoding="utf-8")
    known = read_dictionary(PROJECT_DICT)
    try:
        known.update(make_pronunciations(grammar.words() - known.keys(), read_dictionary(BUNDLED_DICT)))
    except PronunciationError as exc:
        raise EvalError(f"the GPSR words need pronunciations: {exc}") from None
    dictionary.write_text(format_dictionary(known), encoding="utf-8")
    return gram, dictionary


def gpsr_vocabulary(grammar, work: Path) -> Path:
    """``work/gpsr.vocabulary``: the names, places, objects and categories of the GPSR world, one a line."""
    path = work / "gpsr.vocabulary"
    path.write_text("# the GPSR world's names, places, objects and categories (esiaf eval robocup --vocabulary)\n"
                    + "\n".join(grammar.world.vocabulary()) + "\n", encoding="utf-8")
    return path


def gpsr_recogniser(backend: str, language: tuple[Path, Path] | None, vocabulary: Path | None):
    """The recogniser of the GPSR oracle row: pocketsphinx with the GPSR grammar (``language``) or its
    language model, or Whisper free; with the ``vocabulary`` as the asr takes it."""
    from esiaf_services.asr.vocabulary import read_vocabulary
    entries = read_vocabulary(vocabulary) if vocabulary else []
    if backend == "whisper":
        return FreeWhisper(entries)
    from esiaf_services.asr.recognizer import DEFAULT_EXTRA_DICT, PocketsphinxRecognizer
    from esiaf_services.asr.vocabulary import VOCABULARY_WEIGHT, for_pocketsphinx
    extra = language[1] if language else DEFAULT_EXTRA_DICT
    return PocketsphinxRecognizer(16000, grammar=language[0] if language else None, extra_dictionary=extra,
                                  vocabulary=for_pocketsphinx(entries, extra, "vocabulary") if entries else None,
                                  vocabulary_weight=VOCABULARY_WEIGHT)


def oracle_recogniser(pipeline: list[str]):
    """The recogniser of the oracle row: the pipeline's backend and scoring (``--asr``, and
    ``ESIAF_ASR_WHISPER__SCORING``), on the RoboCup questions."""
    backend = backend_of(pipeline)
    if backend == "whisper":
        return ClosedSetOracle(os.environ.get("ESIAF_ASR_WHISPER__SCORING", "acoustic"))
    from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
    from esiaf_services.asr.recognizer import PocketsphinxRecognizer
    return PocketsphinxRecognizer(16000, grammar=ROBOCUP_GRAMMAR)


def parse_snr(text: str) -> tuple[float, float]:
    try:
        low, high = (float(part) for part in text.split(":"))
    except ValueError:
        raise EvalError(f"--snr takes LOW:HIGH in dB (e.g. 5:15), not {text!r}") from None
    if not -10 <= low <= high <= 60:
        raise EvalError(f"--snr {text}: need -10 <= LOW <= HIGH <= 60 dB")
    return low, high


def parse_args(argv: Sequence[str]) -> tuple[argparse.Namespace, list[str]]:
    argv = list(argv)
    options = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(prog="esiaf eval", description="Evaluation harnesses (options after -- go to "
                                     "esiaf run, e.g. -- --asr whisper --no-beamformer)")
    parser.add_argument("task", choices=("robocup",), help="robocup: RoboCup@Home Speech & Person Recognition")
    parser.add_argument("--task", dest="scenario", choices=("questions", "gpsr"), default="questions",
                        help="questions: the 50 questions, two games (default); gpsr: General Purpose Service Robot "
                        "commands from its grammar")
    parser.add_argument("--category", type=int, default=1, help="with --task gpsr: the GPSR grammar's category, "
                        "1-3 (default 1)")
    parser.add_argument("--vocabulary", action="store_true", help="with --task gpsr: the asr gets the GPSR world's "
                        "names, places, objects and categories as its vocabulary (gpsr.vocabulary in the work folder)")
    parser.add_argument("--free", action="store_true", help="with --task gpsr: pocketsphinx recognises with its "
                        "language model instead of the command grammar (Whisper always does)")
    parser.add_argument("--runs", type=int, default=6, help="runs per array (default 6)")
    parser.add_argument("--seed", type=int, default=1, help="random seed of the rooms and games (default 1)")
    parser.add_argument("--snr", default="5:15", help="SNR range in dB, LOW:HIGH (default 5:15)")
    parser.add_argument("--array", action="append", help="array preset (pepper4, respeaker4); repeatable "
                        "(default: both)")
    parser.add_argument("--workdir", type=Path, help="where recordings and logs go (default: a temporary folder)")
    parser.add_argument("--port", type=int, default=8700, help="orchestrator port of the runs (default 8700)")
    parser.add_argument("--no-oracle", action="store_true", help="skip the oracle row")
    parser.add_argument("--json", type=Path, help="also write every run's scores to this file")
    parser.add_argument("--robot-speaks", action="store_true", help="the robot answers each question through its "
                        "loudspeaker (7 cm from the array, its echo 10 dB above the talkers, 100 ms late) while the "
                        "next person already asks; the pipeline runs with --playback")
    return parser.parse_args(argv), options


def check(args: argparse.Namespace) -> None:
    from esiaf.arrays import ArrayError, load_array
    if not 1 <= args.runs <= 1000:
        raise EvalError(f"--runs must be from 1 to 1000, not {args.runs}")
    if not 1 <= args.port <= 65535:
        raise EvalError(f"--port must be from 1 to 65535, not {args.port}")
    args.snr_range = parse_snr(args.snr)
    args.array = args.array or ["pepper4", "respeaker4"]
    for array in args.array:
        try:
            load_array(array)
        except ArrayError as exc:
            raise EvalError(str(exc)) from None
    for needed in (QUESTIONS, KITCHEN):
        if not (DATA / needed).is_file():
            raise EvalError(f"{DATA / needed} is missing: the harness needs the shared test data "
                            f"(set ESIAF_SHARED_DATA to its folder)")
    check_task(args)
    from esiaf.scenes import SceneError, speak
    try:
        speak("test", "slt", 16000)
    except SceneError as exc:
        raise EvalError(f"the harness synthesises its talkers with flite: {exc}") from None


def check_task(args: argparse.Namespace) -> None:
    """The options of ``--task``; with gpsr, its grammar loaded (``args.gpsr``)."""
    if args.scenario != "gpsr":
        if args.vocabulary or args.free:
            raise EvalError("--vocabulary and --free go with --task gpsr (the questions have their grammar)")
        return
    from esiaf.tools.gpsr import GpsrError, load
    if args.robot_speaks:
        raise EvalError("--robot-speaks goes with the questions (the robot answers them), not --task gpsr")
    try:
        args.gpsr = load(DATA / GPSR_FOLDER, args.category)
    except GpsrError as exc:
        raise EvalError(str(exc)) from None


def evaluate(args: argparse.Namespace, options: list[str]) -> list[RunScore]:
    import soundfile

    from esiaf.scenes import render
    pipeline = options if "--without" in options else DEFAULT_PIPELINE + options
    questions = read_questions_and_answers(DATA)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="esiaf-eval-"))
    work.mkdir(parents=True, exist_ok=True)
    gpsr = args.scenario == "gpsr"
    language: tuple[Path, Path] | None = None
    grammar: str | None = "robocup"
    env: dict[str, str] = {}
    vocabulary: Path | None = None
    if gpsr:  # pocketsphinx: the command language as JSGF (unless --free); whisper: free transcription
        language = gpsr_language(args.gpsr, work) if backend_of(pipeline) == "pocketsphinx" and not args.free \
            else None
        grammar = str(language[0]) if language else None
        env = {"ESIAF_ASR_POCKETSPHINX__EXTRA_DICTIONARY": str(language[1])} if language else {}
        if args.vocabulary:
            vocabulary = gpsr_vocabulary(args.gpsr, work)
            env["ESIAF_ASR_VOCABULARY"] = str(vocabulary)
    recogniser = None
    if not args.no_oracle:
        recogniser = gpsr_recogniser(backend_of(pipeline), language, vocabulary) if gpsr \
            else oracle_recogniser(pipeline)
    print(f"eval: {args.scenario}, {args.runs} run(s) per array on {', '.join(args.array)}, SNR {args.snr} dB, "
          f"seed {args.seed}; "
          f"pipeline: esiaf run --fast {' '.join(pipeline)}; work in {work}", file=sys.stderr, flush=True)
    scores = []
    total = args.runs * len(args.array)
    for array in args.array:
        for index in range(args.runs):
            name = f"{array}-run{index + 1}"
            run_dir = work / name
            run_dir.mkdir(exist_ok=True)
            commands = generate_commands(args.gpsr, args.seed, index) if gpsr else []
            scene, games, snr_db = make_scene(index, args.seed, array, args.snr_range, DATA, work, questions,
                                              [c.text for c in commands] if gpsr else None)
            options = pipeline
            if args.robot_speaks:
                options = [*pipeline, "--playback", str(robot_speaks(scene, questions, run_dir))]
            signals, truth = render(scene)
            audio = run_dir / "scene.flac"
            soundfile.write(str(audio), np.round(signals * 32767).astype(np.int16), scene.sample_rate_hz)
            (run_dir / "scene.json").write_text(json.dumps(truth, indent=2) + "\n")
            asked = [Question(game, u["text"], u["azimuth_deg"], u["start_s"], u["end_s"])
                     for game, u in zip(games, truth["utterances"], strict=True)] if not gpsr else []
            said = [SpokenCommand(c.text, [(s.kind, s.value) for s in c.slots], u["start_s"], u["end_s"])
                    for c, u in zip(commands, truth["utterances"], strict=True)] if gpsr else []
            try:
                fused, wall_s = run_pipeline(audio, array, options, run_dir, args.port, name, grammar, env)
            except EvalError as exc:  # scored as a run that answered nothing; the others go on
                print(f"eval: {exc}", file=sys.stderr, flush=True)
                fused, wall_s = [], 0.0
            run = RunScore(name, snr_db, scene.rt60_s, asked, audio_s=truth["duration_s"], pipeline_s=wall_s,
                           fused=len(fused), failed=not wall_s, commands=said)
            run.spurious = score_commands(said, fused) if gpsr else score(asked, fused)
            if recogniser is not None and gpsr:
                oracle_commands(signals, said, scene.sample_rate_hz, recogniser)
            elif recogniser is not None:
                run.oracle_recognised = oracle(signals, asked, scene.sample_rate_hz, recogniser)
            (run_dir / "fused.json").write_text(json.dumps(fused, indent=1) + "\n")
            scores.append(run)
            if gpsr:
                print(f"eval: [{len(scores)}/{total}] {name}: SNR {snr_db:.1f} dB, RT60 {scene.rt60_s:.2f} s: "
                      f"{sum(c.exact for c in said)}/{len(said)} commands exact, {run.spurious} spurious"
                      + (f"; oracle {sum(normalise(c.oracle) == normalise(c.text) for c in said)}/{len(said)}"
                         if recogniser else ""),
                      file=sys.stderr, flush=True)
                continue
            print(f"eval: [{len(scores)}/{total}] {name}: SNR {snr_db:.1f} dB, RT60 {scene.rt60_s:.2f} s: "
                  f"{sum(q.recognised for q in asked)}/10 questions, "
                  f"{sum(direction_right(q) for q in asked)}/10 directions, {run.spurious} spurious, "
                  f"{run.points} points" + (f"; oracle {run.oracle_recognised}/10" if recogniser else ""),
                  file=sys.stderr, flush=True)
    return scores


def generate_commands(grammar, seed: int, index: int) -> list:
    """The GPSR commands of run ``index``: the same for the same seed and index, whatever the array."""
    from esiaf.tools.gpsr import generate
    return generate(grammar, GPSR_COMMANDS_PER_RUN, seed * 100_003 + index)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args, options = parse_args(sys.argv[2:] if argv is None else argv)
        check(args)
        scores = evaluate(args, options)
    except EvalError as exc:
        print(f"eval: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("eval: stopped", file=sys.stderr)
        return 130
    gpsr = args.scenario == "gpsr"
    figures = (gpsr_summary if gpsr else summary)(scores, not args.no_oracle)
    print((gpsr_table if gpsr else table)(scores, figures, not args.no_oracle))
    for name, value in figures.items():
        print(f"{name}={value:.3f}" if isinstance(value, float) else f"{name}={value}")
    if args.json:
        args.json.write_text(json.dumps({"figures": figures, "runs": [
            {"name": r.name, "snr_db": r.snr_db, "rt60_s": r.rt60_s, "spurious": r.spurious, "points": r.points,
             "fused": r.fused, "oracle_recognised": r.oracle_recognised, "pipeline_s": r.pipeline_s,
             "questions": [q.__dict__ for q in r.questions], "commands": [c.__dict__ for c in r.commands]}
            for r in scores]}, indent=1) + "\n")
    return 0

"""How Whisper is best given a vocabulary: GPSR commands spoken clean by flite, decoded by tiny.en
without one, with it as initial prompt, with it as faster-whisper's ``hotwords``, and each of the
two with the invented tail dropped (``whisper.invented_tail``).

    python -m bench.whisper_vocabulary [--count 24] [--seed 7]

The vocabulary is the GPSR world's (``World.vocabulary``, the shared data's XML files), as the asr
prompts with it (``vocabulary.prompt``); the commands are drawn from the Category 1 grammar, the
voices taken in turn (slt, kal16, awb, rms). A command is exact when its words are the decode's.
Decodes are as the asr's (beam 5, word times, no conditioning on previous text); faster-whisper's
temperature fallback samples, so a row varies by a command or two from run to run.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if __name__ == "__main__":
    sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402

import numpy as np  # noqa: E402

VOICES = ("slt", "kal16", "awb", "rms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.whisper_vocabulary", description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=24, help="commands (default 24)")
    parser.add_argument("--seed", type=int, default=7, help="seed of the commands (default 7)")
    args = parser.parse_args(argv)
    from esiaf.scenes import speak
    from esiaf.tools.evaluation import DATA, GPSR_FOLDER
    from esiaf.tools.gpsr import generate, load
    from esiaf.tools.robocup_scoring import normalise
    from esiaf_services.asr.vocabulary import prompt
    from esiaf_services.asr.whisper import WhisperRecognizer, invented_tail, within_segment

    whisper = WhisperRecognizer()
    grammar = load(DATA / GPSR_FOLDER)
    text = prompt(grammar.world.vocabulary(), whisper.model.hf_tokenizer)[0]
    ways = {"none": {}, "initial prompt": {"initial_prompt": text}, "hotwords": {"hotwords": text}}
    exact = {name: 0 for name in [*ways, *(f"{w}, tail dropped" for w in ways if w != "none")]}
    commands = generate(grammar, args.count, args.seed)
    for index, command in enumerate(commands):
        samples = speak(command.text, VOICES[index % len(VOICES)], 16000).astype(np.float32)
        for name, options in ways.items():
            segments, _ = whisper.model.transcribe(samples, language="en", beam_size=5, word_timestamps=True,
                                                   condition_on_previous_text=False, vad_filter=False, **options)
            segments = list(segments)
            heard = within_segment(segments, samples.size / 16000)[0]
            exact[name] += normalise(heard) == command.words
            if name != "none":
                kept = segments[:len(segments) - invented_tail(segments)]
                exact[f"{name}, tail dropped"] += normalise(within_segment(kept, samples.size / 16000)[0]) \
                    == command.words
    print("| vocabulary given as | commands exact |\n|---|---|")
    for name, count in exact.items():
        print(f"| {name} | {count}/{len(commands)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

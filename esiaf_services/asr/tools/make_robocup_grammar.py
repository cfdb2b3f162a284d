"""Generate the RoboCup@Home question grammar and the project pronunciation dictionary.

Run from the repository root (regenerates both files, deterministically)::

    python -m esiaf_services.asr.tools.make_robocup_grammar [QUESTIONS_TSV]

Reads the 50 predefined questions (``index<TAB>question<TAB>answer``), normalises them (lower case,
hyphens to spaces, punctuation except inner apostrophes removed, digits kept as tokens) and writes

* ``esiaf_services/asr/grammars/robocup.gram``: JSGF, one public rule ``<question>`` alternating the sentences;
* ``esiaf_services/asr/dict/project.dict``: a pronunciation for every grammar word missing from pocketsphinx's
  bundled ``cmudict-en-us.dict``.

How a missing word gets its pronunciation (in this order, all reproducible):

1. all-digit tokens (``3``, ``1915``): Debian flite's own number expansion (``flite -pw``, e.g.
   ``1915`` -> ``nineteen fifteen``), then the bundled-dictionary pronunciations (first variant) of
   the spelled-out words, concatenated;
2. other words: flite's lexicon / letter-to-sound rules (``t2p WORD``), flite phones mapped to the 39
   CMUdict phones (stress digits dropped, ``ax`` -> ``AH``, ``axr`` -> ``ER``, ``pau`` removed);
3. ``EXTRA_PRONUNCIATIONS`` below, an explicit hand table, adds the conventional pronunciation as an
   alternative (``word(2)``) where flite's guess differs; flite's version stays first because it is
   what the flite voices used in tests actually say.

The script fails (exit status 1) if a word still has no pronunciation.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
from pathlib import Path

from esiaf_services.asr.lexicon import (
    BUNDLED_DICT,
    CMU_PHONES,
    PROJECT_DICT,
    ROBOCUP_GRAMMAR,
    Pronunciation,
    format_dictionary,
    normalise_sentence,
    read_dictionary,
    read_questions,
)

LOGGER = logging.getLogger(__name__)

DEFAULT_QUESTIONS_TSV = Path(__file__).resolve().parents[4] / "shared" / "data" / "robocup" / "questions.tsv"

# flite's US English phone set -> CMUdict phones. Identical names map to themselves (upper-cased).
FLITE_TO_CMU_PHONE = {
    **{phone.lower(): phone for phone in CMU_PHONES},
    "ax": "AH",  # schwa: CMUdict writes unstressed AH
    "axr": "ER",  # r-coloured schwa
}
FLITE_SILENCE_PHONES = frozenset({"pau", "h#", "brth"})

# Hand corrections, added as alternatives after flite's pronunciation (which stays first).
EXTRA_PRONUNCIATIONS: dict[str, list[Pronunciation]] = {
    # "AI's" = the letters A-I; flite reads the word "ai's" (AY Z).
    "ai's": [("EY", "AY", "Z")],
    # Yonge Street (Toronto) is said "young"; flite guesses Y AO N JH.
    "yonge": [("Y", "AH", "NG")],
    # Elon Musk: "EE-lon"; flite guesses IH L AH N.
    "elon": [("IY", "L", "AA", "N")],
    # nano-bot, chat-bot: flite reduces the vowels of "nano" and "bot".
    "nanobot": [("N", "AE", "N", "OW", "B", "AA", "T")],
    "chatbot": [("CH", "AE", "T", "B", "AA", "T")],
    # Hans Moravec: "MOR-a-vek"; flite guesses M ER AA V IH K S.
    "moravec's": [("M", "AO", "R", "AH", "V", "EH", "K", "S")],
}


class PronunciationError(RuntimeError):
    """No pronunciation could be made for a word."""


def _run_tool(arguments: list[str]) -> str:
    if shutil.which(arguments[0]) is None:
        raise PronunciationError(f"{arguments[0]} not found: install Debian's flite (apt-get install flite)")
    completed = subprocess.run(arguments, capture_output=True, text=True, check=False)
    if completed.returncode != 0:
        raise PronunciationError(f"{' '.join(arguments)} failed: {completed.stderr.strip()}")
    return completed.stdout


def flite_phones(word: str) -> Pronunciation:
    """``word`` by flite's lexicon and letter-to-sound rules (``t2p``), in CMUdict phones."""
    phones = []
    for flite_phone in _run_tool(["t2p", word]).split():
        name = flite_phone.rstrip("012")
        if name in FLITE_SILENCE_PHONES:
            continue
        if name not in FLITE_TO_CMU_PHONE:
            raise PronunciationError(f"t2p gave phone {flite_phone!r} for {word!r}: no CMUdict mapping")
        phones.append(FLITE_TO_CMU_PHONE[name])
    if not phones:
        raise PronunciationError(f"t2p gave no phones for {word!r}")
    return tuple(phones)


def spelled_number_phones(number: str, bundled: dict[str, list[Pronunciation]]) -> Pronunciation:
    """Spell ``number`` out as flite says it, then concatenate the bundled pronunciations of the words."""
    spelled_words = _run_tool(["flite", "-pw", "-t", number, "-o", "none"]).split()
    if not spelled_words:
        raise PronunciationError(f"flite -pw gave no words for {number!r}")
    missing = [word for word in spelled_words if word not in bundled]
    if missing:
        raise PronunciationError(f"{number!r} spells as {spelled_words}; {missing} are not in {BUNDLED_DICT}")
    return tuple(phone for word in spelled_words for phone in bundled[word][0])


def make_pronunciations(words: set[str], bundled: dict[str, list[Pronunciation]],
                        failed: list[str] | None = None) -> dict[str, list[Pronunciation]]:
    """Pronunciations for every word of ``words`` that is missing from the bundled dictionary. A word
    flite cannot say raises ``PronunciationError``, or, given a ``failed`` list, is added to it."""
    entries: dict[str, list[Pronunciation]] = {}
    for word in sorted(words - bundled.keys()):
        try:
            first = spelled_number_phones(word, bundled) if word.isdigit() else flite_phones(word)
        except PronunciationError as error:
            if failed is None:
                raise
            LOGGER.debug("no pronunciation for %r: %s", word, error)
            failed.append(word)
            continue
        variants = [first]
        for extra in EXTRA_PRONUNCIATIONS.get(word, []):
            if extra not in variants:
                variants.append(extra)
        entries[word] = variants
        LOGGER.debug("%s: %s", word, " | ".join(" ".join(phones) for phones in variants))
    return entries


def format_grammar(sentences: list[str], source: Path) -> str:
    """JSGF text with one public rule ``<question>`` alternating ``sentences``."""
    alternatives = "\n    | ".join(sentences)
    return (
        "#JSGF V1.0;\n\n"
        f"/* Generated by esiaf_services/asr/tools/make_robocup_grammar.py from {source.name}; do not edit. */\n\n"
        "grammar robocup;\n\n"
        f"public <question> = {alternatives}\n    ;\n"
    )


def generate(questions_tsv: Path, grammar_path: Path, dictionary_path: Path) -> None:
    """Write the grammar and the project dictionary for the questions in ``questions_tsv``."""
    sentences = []
    for _index, question in read_questions(questions_tsv):
        sentence = normalise_sentence(question)
        if sentence and sentence not in sentences:
            sentences.append(sentence)
    words = {word for sentence in sentences for word in sentence.split()}
    bundled = read_dictionary(BUNDLED_DICT)
    entries = make_pronunciations(words, bundled)
    for word, variants in sorted(entries.items()):
        LOGGER.info("%s: %s", word, " | ".join(" ".join(phones) for phones in variants))
    unused = EXTRA_PRONUNCIATIONS.keys() - entries.keys()
    if unused:
        LOGGER.warning("hand corrections for words not needed by the grammar: %s", sorted(unused))
    still_missing = sorted(words - bundled.keys() - entries.keys())
    if still_missing:
        raise PronunciationError(f"no pronunciation for {still_missing}")
    grammar_path.parent.mkdir(parents=True, exist_ok=True)
    dictionary_path.parent.mkdir(parents=True, exist_ok=True)
    grammar_path.write_text(format_grammar(sentences, questions_tsv), encoding="utf-8")
    dictionary_path.write_text(format_dictionary(entries), encoding="utf-8")
    LOGGER.info("wrote %s (%d sentences, %d words)", grammar_path, len(sentences), len(words))
    LOGGER.info("wrote %s (%d words missing from the bundled dictionary)", dictionary_path, len(entries))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("questions", nargs="?", type=Path, default=DEFAULT_QUESTIONS_TSV,
                        help=f"index<TAB>question<TAB>answer file (default {DEFAULT_QUESTIONS_TSV})")
    parser.add_argument("--grammar", type=Path, default=ROBOCUP_GRAMMAR, help="JSGF file to write")
    parser.add_argument("--dictionary", type=Path, default=PROJECT_DICT, help="project dictionary to write")
    arguments = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        generate(arguments.questions, arguments.grammar, arguments.dictionary)
    except (OSError, ValueError, PronunciationError) as error:
        LOGGER.error("error: %s", error)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

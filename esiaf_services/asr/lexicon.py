"""Text normalisation and pronunciation-dictionary helpers shared by the recogniser and its tools.

The recogniser uses pocketsphinx's bundled US English models; words are written the way the bundled
CMU dictionary writes them (lower case, apostrophes kept, no other punctuation).  Project words that
the bundled dictionary lacks live in ``dict/project.dict`` (same format, see ``README.md``).
"""

from __future__ import annotations

import re
from pathlib import Path

import pocketsphinx

ASR_DIR = Path(__file__).resolve().parent
PROJECT_DICT = ASR_DIR / "dict" / "project.dict"
ROBOCUP_GRAMMAR = ASR_DIR / "grammars" / "robocup.gram"

BUNDLED_MODEL_DIR = Path(pocketsphinx.get_model_path("en-us"))
BUNDLED_ACOUSTIC_MODEL = BUNDLED_MODEL_DIR / "en-us"
BUNDLED_LANGUAGE_MODEL = BUNDLED_MODEL_DIR / "en-us.lm.bin"
BUNDLED_DICT = BUNDLED_MODEL_DIR / "cmudict-en-us.dict"

# The 39 CMUdict phones (without stress marks): the phone set of the bundled acoustic model.
CMU_PHONES = frozenset([
    "AA", "AE", "AH", "AO", "AW", "AY", "B", "CH", "D", "DH", "EH", "ER", "EY", "F", "G", "HH", "IH", "IY", "JH", "K",
    "L", "M", "N", "NG", "OW", "OY", "P", "R", "S", "SH", "T", "TH", "UH", "UW", "V", "W", "Y", "Z", "ZH",
])

_ALTERNATIVE_SUFFIX = re.compile(r"\(\d+\)$")
_NOT_WORD_CHARACTER = re.compile(r"[^a-z0-9' ]+")

Pronunciation = tuple[str, ...]


class DictionaryFormatError(ValueError):
    """A pronunciation dictionary line is malformed or uses an unknown phone."""


def normalise_sentence(text: str) -> str:
    """Lower-case ``text``, turn hyphens into spaces and drop all punctuation except inner apostrophes.

    ``"Are self-driving cars safe?"`` becomes ``"are self driving cars safe"``; ``"What's"`` stays
    ``"what's"``; digits stay digits (``"1915"``), their pronunciations come from the project dictionary.
    """
    lowered = text.lower().replace("-", " ")
    cleaned = _NOT_WORD_CHARACTER.sub(" ", lowered)
    tokens = (token.strip("'") for token in cleaned.split())
    return " ".join(token for token in tokens if token)


def base_word(entry: str) -> str:
    """``"word(2)"`` -> ``"word"``: the spoken word behind a dictionary entry or alternative."""
    return _ALTERNATIVE_SUFFIX.sub("", entry)


def read_dictionary(path: Path) -> dict[str, list[Pronunciation]]:
    """Read a CMUdict-format file: ``word PH1 PH2 ...`` per line, alternatives written ``word(2) ...``.

    Returns word -> pronunciations in file order.  Raises ``OSError`` if the file cannot be read and
    ``DictionaryFormatError`` (naming file and line) for a line without phones or with a phone outside
    the 39 CMUdict phones.
    """
    entries: dict[str, list[Pronunciation]] = {}
    with path.open(encoding="utf-8") as stream:
        for line_number, line in enumerate(stream, start=1):
            fields = line.split()
            if not fields or fields[0].startswith(";;;"):
                continue
            word, phones = fields[0], tuple(fields[1:])
            where = f"{path}:{line_number}"
            if not phones:
                raise DictionaryFormatError(f"{where}: word {word!r} has no phones")
            unknown = [phone for phone in phones if phone not in CMU_PHONES]
            if unknown:
                raise DictionaryFormatError(
                    f"{where}: word {word!r} uses phones {unknown} outside the 39 CMUdict phones"
                )
            entries.setdefault(base_word(word).lower(), []).append(phones)
    return entries


def format_dictionary(entries: dict[str, list[Pronunciation]]) -> str:
    """CMUdict text for ``entries``: sorted by word, alternatives numbered ``word(2)``, ``word(3)``..."""
    lines = []
    for word in sorted(entries):
        for number, phones in enumerate(entries[word], start=1):
            name = word if number == 1 else f"{word}({number})"
            lines.append(f"{name} {' '.join(phones)}")
    return "\n".join(lines) + "\n"


def read_questions(path: Path) -> list[tuple[int, str]]:
    """(index, question) pairs from a ``index<TAB>question<TAB>answer`` file; ``#`` lines are comments."""
    questions = []
    with path.open(encoding="utf-8") as stream:
        for line_number, line in enumerate(stream, start=1):
            if not line.strip() or line.startswith("#"):
                continue
            fields = line.rstrip("\n").split("\t")
            if len(fields) < 2 or not fields[0].strip().isdigit():
                raise ValueError(f"{path}:{line_number}: expected index<TAB>question<TAB>answer")
            questions.append((int(fields[0]), fields[1].strip()))
    return questions

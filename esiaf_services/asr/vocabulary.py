"""A deployment's vocabulary (``vocabulary: FILE``): the names, places and objects it expects, read
from a file, and what each backend makes of them.

The file holds one entry a line ("Skyler", "side table", "cleaning stuff"); ``#`` starts a comment,
blank lines and repeated entries (ignoring case) are skipped. It is checked when the settings are
loaded, so a bad file is one line at start-up: missing, unreadable, not UTF-8, without entries, or
past the cap (``MAX_ENTRIES`` entries, ``MAX_BYTES`` bytes).

- **Whisper** is prompted with the entries, spelled as written, in file order ("Skyler, side table,
  cleaning stuff."): faster-whisper puts an initial prompt where Whisper reads the text that came
  before, so the decoder favours those spellings. The prompt holds what fits in
  ``MAX_PROMPT_TOKENS`` (half of Whisper's 448-token context, less one, as faster-whisper cuts it);
  entries past it are left out, and :func:`prompt` says how many.
- **pocketsphinx** gets a pronunciation for each word of the entries its dictionary lacks, made
  as the project's other words are (flite, ``tools/make_robocup_grammar.make_pronunciations``);
  words flite cannot say, or that are not written in the letters and digits of the bundled
  dictionary ("Zoë"), are named in one log line and the rest are used (:func:`pronunciations`).
  With the language model, words it lacks are added to it (``recognizer.py``).
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

from esiaf_services.asr.lexicon import Pronunciation

log = logging.getLogger(__name__)

MAX_ENTRIES = 1000  # a deployment's names, places and objects; more is not a vocabulary but a language
MAX_BYTES = 64 * 1024
MAX_PROMPT_TOKENS = 223  # faster-whisper keeps the last max_length // 2 - 1 tokens of a prompt
VOCABULARY_WEIGHT = 10.0  # pocketsphinx: "skyler" said by flite is "tyler" without, "schuyler" at 1, "skyler" at 10
SPELLABLE = re.compile(r"[a-z0-9']+")  # the bundled dictionary's letters


@dataclass
class Vocabulary:
    """What pocketsphinx takes of a vocabulary: its words, and pronunciations for those it lacks."""
    words: list[str]
    pronunciations: dict[str, list[Pronunciation]] = field(default_factory=dict)


class VocabularyError(ValueError):
    """A vocabulary file that cannot be used; the message names the file and what is wrong."""


def read_vocabulary(path: str | Path) -> list[str]:
    """The entries of the vocabulary file ``path``, in file order, without comments or repeats."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise VocabularyError(f"vocabulary {path} has {size} bytes: at most {MAX_BYTES} (its names, places "
                                  f"and objects, one a line)")
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise VocabularyError(f"vocabulary {path} not found") from None
    except IsADirectoryError:
        raise VocabularyError(f"vocabulary {path} is a folder, not a file") from None
    except OSError as exc:
        raise VocabularyError(f"cannot read vocabulary {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise VocabularyError(f"vocabulary {path} is not UTF-8 text") from None
    entries: dict[str, str] = {}
    for line in text.splitlines():
        entry = " ".join(line.split("#", 1)[0].split())
        if entry:
            entries.setdefault(entry.casefold(), entry)
    if not entries:
        raise VocabularyError(f"vocabulary {path} holds no entries (one name, place or object a line)")
    if len(entries) > MAX_ENTRIES:
        raise VocabularyError(f"vocabulary {path} has {len(entries)} entries: at most {MAX_ENTRIES}")
    return list(entries.values())


def prompt(entries: list[str], tokenizer, budget: int = MAX_PROMPT_TOKENS) -> tuple[str, int]:
    """Whisper's prompt of ``entries`` ("A, B, C."), as many as fit in ``budget`` tokens of
    ``tokenizer`` (a ``tokenizers.Tokenizer``, faster-whisper's ``hf_tokenizer``), and how many it holds."""
    kept: list[str] = []
    for entry in entries:
        text = " " + ", ".join([*kept, entry]) + "."
        if len(tokenizer.encode(text, add_special_tokens=False).ids) > budget:
            break
        kept.append(entry)
    return (", ".join(kept) + ".", len(kept)) if kept else ("", 0)


def for_pocketsphinx(entries: list[str], extra_dictionary: str | Path | None, source: str) -> Vocabulary:
    """:func:`pronunciations` of ``entries`` against the bundled dictionary and ``extra_dictionary``.
    Raises ``OSError`` or ``DictionaryFormatError`` for a dictionary that cannot be read."""
    from esiaf_services.asr.lexicon import BUNDLED_DICT, read_dictionary
    known = read_dictionary(BUNDLED_DICT)
    if extra_dictionary:
        known.update(read_dictionary(Path(extra_dictionary)))
    vocabulary = pronunciations(entries, known, source)
    log.info("%s: %d entries, %d words, %d pronunciations made", source, len(entries), len(vocabulary.words),
             len(vocabulary.pronunciations))
    return vocabulary


def words(entries: list[str]) -> tuple[list[str], list[str]]:
    """The words of ``entries`` as the bundled dictionary writes them (lower case, hyphens split),
    and those that cannot be written so, each once, in order."""
    spelled: dict[str, None] = {}
    unspellable: dict[str, None] = {}
    for entry in entries:
        for token in entry.lower().replace("-", " ").split():
            word = token.strip(".,;:!?\"()").strip("'")
            if SPELLABLE.fullmatch(word):
                spelled[word] = None
            elif word or token:
                unspellable[token] = None
    return list(spelled), list(unspellable)


def pronunciations(entries: list[str], known: dict[str, list[Pronunciation]], source: str = "vocabulary"
                   ) -> Vocabulary:
    """The words of ``entries`` (as :func:`words`) and pronunciations for those ``known`` lacks (flite,
    as the project dictionary's). Words without one are named in one warning and left out."""
    from esiaf_services.asr.tools.make_robocup_grammar import make_pronunciations
    spelled, unpronounceable = words(entries)
    made = make_pronunciations(set(spelled), known, failed=unpronounceable)
    if unpronounceable:
        log.warning("%s: no pronunciation for %d word(s), left out: %s", source, len(unpronounceable),
                    ", ".join(unpronounceable))
    return Vocabulary([word for word in spelled if word not in unpronounceable], made)

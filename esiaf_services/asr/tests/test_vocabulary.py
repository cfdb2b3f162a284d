"""The asr's ``vocabulary`` (vocabulary.py): the file read and its bad forms refused, and real
recognisers on flite speech, pocketsphinx and Whisper tiny.en, with and without it."""
from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from esiaf.settings import SettingsError, load_settings
from esiaf_services.asr.matching import normalise
from esiaf_services.asr.service import Asr, AsrSettings
from esiaf_services.asr.vocabulary import MAX_BYTES, MAX_ENTRIES, VocabularyError, read_vocabulary, words

GPSR_NAMES_AND_OBJECTS = ["Skyler", "Robin", "Patricia", "cascade pod", "scrubby", "sponge", "kitchen", "side table"]


def vocabulary_file(tmp_path: Path, *lines: str, name: str = "vocabulary.txt") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def flite(text: str, voice: str = "slt") -> np.ndarray:
    from esiaf.scenes import SceneError, speak
    try:
        return speak(text, voice, 16000).astype(np.float32)
    except SceneError as exc:
        pytest.skip(str(exc))


def test_entries_in_file_order_without_comments_blanks_or_repeats(tmp_path):
    path = vocabulary_file(tmp_path, "# the deployment's names", "Skyler", "", "  side   table  # a place",
                           "skyler", "cascade pod")
    assert read_vocabulary(path) == ["Skyler", "side table", "cascade pod"]


@pytest.mark.parametrize("make, complaint", [
    (lambda tmp: tmp / "missing.txt", "not found"),
    (lambda tmp: tmp, "is a folder"),
    (lambda tmp: vocabulary_file(tmp, "# only a comment", ""), "holds no entries"),
    (lambda tmp: (tmp / "latin1.txt", (tmp / "latin1.txt").write_bytes("Zo\xeb\n".encode("latin-1")))[0],
     "not UTF-8"),
    (lambda tmp: vocabulary_file(tmp, *(f"w{i}" for i in range(MAX_ENTRIES + 1))), f"at most {MAX_ENTRIES}"),
    (lambda tmp: vocabulary_file(tmp, "x" * (MAX_BYTES + 1)), f"at most {MAX_BYTES}"),
], ids=["missing", "folder", "empty", "not utf-8", "too many entries", "too many bytes"])
def test_a_bad_file_is_one_clear_error_when_the_settings_are_loaded(tmp_path, make, complaint):
    path = make(tmp_path)
    with pytest.raises(VocabularyError, match=complaint):
        read_vocabulary(path)
    with pytest.raises(SettingsError, match=complaint) as raised:
        load_settings(AsrSettings, "asr", env={"ESIAF_ASR_VOCABULARY": str(path)})
    assert "\n" not in str(raised.value)


def test_words_are_spelled_as_the_dictionary_spells_them_and_the_rest_named():
    spelled, unspellable = words(["Skyler", "side-table", "Zoë", "O'Brien's", "7up", "東京"])
    assert spelled == ["skyler", "side", "table", "o'brien's", "7up"]
    assert unspellable == ["zoë", "東京"]


def pocketsphinx_text(samples: np.ndarray, vocabulary: Path | None) -> str:
    settings = load_settings(AsrSettings, "asr", env={}, vocabulary=str(vocabulary) if vocabulary else "")
    asr = Asr(settings)
    asr.setup()
    recognizer = asr._new_decoder()
    return recognizer.recognise((np.clip(samples, -1, 1) * 32767).astype("<i2").tobytes())[0].text


def test_pocketsphinx_says_a_name_it_lacks_once_the_vocabulary_has_it(tmp_path, caplog):
    """"Skyler" is in neither the bundled nor the project dictionary: without the vocabulary
    pocketsphinx cannot say it; with it, flite's pronunciation is added and the name recognised. A
    word it cannot pronounce ("Zoë") is named in one warning and the rest are used."""
    speech = flite("bring the coke to skyler")
    assert "skyler" not in pocketsphinx_text(speech, None).split()
    path = vocabulary_file(tmp_path, "Skyler", "Zoë", "東京", "coke")
    with caplog.at_level(logging.WARNING, logger="esiaf_services.asr.vocabulary"):
        heard = pocketsphinx_text(speech, path)
    assert "skyler" in heard.split(), heard
    named = [r.getMessage() for r in caplog.records if "no pronunciation" in r.getMessage()]
    assert len(named) == 1 and "zoë" in named[0] and "東京" in named[0] and "skyler" not in named[0], named


@pytest.fixture(scope="module")
def whisper():
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf_services.asr.whisper import WhisperRecognizer
    return WhisperRecognizer(n_best=1)


def whisper_asr(vocabulary: Path, whisper) -> Asr:
    asr = Asr(load_settings(AsrSettings, "asr", env={}, backend="whisper", vocabulary=str(vocabulary)))
    asr.whisper = whisper  # the module's model, not one more (setup() would load its own)
    asr._prompt_with(read_vocabulary(vocabulary))
    return asr


@pytest.mark.parametrize("command, voice, slots", [
    ("Give the cascade pod to Skyler in the kitchen.", "kal16", ("cascade pod", "skyler", "kitchen")),
    ("Tell Patricia to take the sponge.", "rms", ("patricia", "sponge")),
])
def test_whisper_writes_the_names_and_objects_right_with_the_vocabulary(tmp_path, whisper, command, voice, slots):
    """Whisper tiny.en mishears the names and objects of these flite commands ("Give the cascade part a
    skylare in the kitchen", "tail patricher to take the sponge"); prompted with the vocabulary it writes
    them right. Only the names and objects are asserted: its int8 decoding of the small words differs
    between CPUs ("take this sponge" on one, "take the sponge" on another)."""
    def heard_all(hypotheses) -> bool:
        heard = f" {' '.join(normalise(hypotheses[0].text))} " if hypotheses else ""
        return all(f" {slot} " in heard for slot in slots)

    speech = flite(command, voice)
    without = whisper.recognise(speech).hypotheses
    assert not heard_all(without), without
    asr = whisper_asr(vocabulary_file(tmp_path, *GPSR_NAMES_AND_OBJECTS), whisper)
    assert asr.prompt is not None and asr.prompt.startswith("Skyler, Robin")
    with_it = whisper.recognise(speech, prompt=asr.prompt).hypotheses
    assert heard_all(with_it), with_it


def test_whisper_is_prompted_with_as_many_entries_as_fit(tmp_path, whisper, caplog):
    from esiaf_services.asr.vocabulary import MAX_PROMPT_TOKENS
    entries = [f"Name{i} Surname{i}" for i in range(200)]
    with caplog.at_level(logging.INFO, logger="esiaf_services.asr.service"):
        asr = whisper_asr(vocabulary_file(tmp_path, *entries), whisper)
    assert asr.prompt is not None
    tokens = whisper.model.hf_tokenizer.encode(" " + asr.prompt, add_special_tokens=False).ids
    kept = asr.prompt.rstrip(".").split(", ")
    assert MAX_PROMPT_TOKENS - 10 < len(tokens) <= MAX_PROMPT_TOKENS and kept == entries[:len(kept)]
    assert any(f"{len(kept)} in Whisper's prompt (the rest past" in r.getMessage() for r in caplog.records)


def test_a_tail_whisper_invents_after_a_prompt_is_dropped():
    """Faster-whisper's segments of "Find the food in the bedroom" (awb) decoded with the GPSR
    vocabulary as prompt, as they came: a second segment "Thank you." the speaker never said."""
    from esiaf_services.asr.whisper import invented_tail

    def segment(*timed):
        return SimpleNamespace(words=[SimpleNamespace(word=w, start=s, end=e, probability=p) for w, s, e, p in timed])
    said = segment((" Find", 0.0, 0.62, 0.58), (" the", 0.62, 0.88, 0.98), (" food", 0.88, 1.04, 0.99),
                   (" in", 1.04, 1.26, 0.99), (" the", 1.26, 1.4, 0.96), (" bedroom.", 1.4, 1.7, 0.7))
    thanks = segment((" Thank", 1.7, 1.72, 0.07), (" you.", 1.72, 1.82, 0.98))
    okay = segment((" Okay.", 2.32, 2.58, 0.01))
    assert invented_tail([said, thanks]) == 1 and invented_tail([said, thanks, okay]) == 2
    assert invented_tail([said]) == 0 and invented_tail([thanks]) == 0  # the first segment always stays
    assert invented_tail([said, said]) == 0


@pytest.mark.parametrize("name", ["agneta", "adelbert"])
def test_a_name_the_language_model_lacks_is_added_to_it(name):
    """The bundled dictionary has these names, its language model does not: pocketsphinx hears
    something else without the vocabulary and the name with it (the model's search made anew)."""
    from esiaf_services.asr.recognizer import PocketsphinxRecognizer
    from esiaf_services.asr.vocabulary import VOCABULARY_WEIGHT, Vocabulary
    pcm = (np.clip(flite(f"bring the coke to {name}"), -1, 1) * 32767).astype("<i2").tobytes()
    without = PocketsphinxRecognizer(extra_dictionary=None).recognise(pcm)[0].text
    with_it = PocketsphinxRecognizer(extra_dictionary=None, vocabulary=Vocabulary([name]),
                                     vocabulary_weight=VOCABULARY_WEIGHT).recognise(pcm)[0].text
    assert name not in without.split() and name in with_it.split(), (without, with_it)

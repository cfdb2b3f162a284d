"""Tests of the pocketsphinx recogniser, the RoboCup grammar and the project dictionary."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
import wave
from pathlib import Path
from types import ModuleType

import pytest

from esiaf_services.asr.lexicon import (
    BUNDLED_DICT,
    PROJECT_DICT,
    ROBOCUP_GRAMMAR,
    normalise_sentence,
    read_dictionary,
    read_questions,
)
from esiaf_services.asr.recognizer import (
    MIN_CONFIDENCE,
    PocketsphinxRecognizer,
    RecognizerError,
)

REPO_ROOT = Path(__file__).resolve().parents[3]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
GOFORWARD_RAW = SHARED_DATA / "speech" / "pocketsphinx" / "goforward.raw"
QUESTIONS_TSV = SHARED_DATA / "robocup" / "questions.tsv"

needs_flite = pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
needs_goforward = pytest.mark.skipif(not GOFORWARD_RAW.is_file(), reason=f"{GOFORWARD_RAW} is absent")
needs_questions = pytest.mark.skipif(not QUESTIONS_TSV.is_file(), reason=f"{QUESTIONS_TSV} is absent")

# Originally-missing words: rcmp, captcha, chatbot, 1915.
SPOKEN_QUESTIONS = [
    "How big is the RCMP?",
    "What does CAPTCHA stands for?",
    "What is a chatbot?",
    "What's the name of the bear cub exported from Canada to the London Zoo in 1915?",
]


@pytest.fixture(scope="module")
def grammar_recogniser() -> PocketsphinxRecognizer:
    return PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR)


@pytest.fixture(scope="module")
def language_model_recogniser() -> PocketsphinxRecognizer:
    return PocketsphinxRecognizer()


@pytest.fixture(scope="module")
def synthesiser() -> ModuleType:
    path = REPO_ROOT / "scripts" / "synth_questions.py"
    spec = importlib.util.spec_from_file_location("synth_questions", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def grammar_sentences() -> list[str]:
    """The alternatives of the grammar's public rule."""
    text = ROBOCUP_GRAMMAR.read_text(encoding="utf-8")
    body = text.split("public <question> =", 1)[1].rsplit(";", 1)[0]
    return [" ".join(alternative.split()) for alternative in body.split("|")]


def known_words() -> set[str]:
    return set(read_dictionary(BUNDLED_DICT)) | set(read_dictionary(PROJECT_DICT))


@needs_goforward
def test_goforward_decodes_with_language_model(language_model_recogniser: PocketsphinxRecognizer) -> None:
    hypotheses = language_model_recogniser.recognise(GOFORWARD_RAW.read_bytes())
    assert hypotheses[0].text == "go forward ten meters"
    assert [word.word for word in hypotheses[0].words] == ["go", "forward", "ten", "meters"]
    duration_s = GOFORWARD_RAW.stat().st_size / 2 / 16000
    times_s = [time_s for word in hypotheses[0].words for time_s in (word.start_s, word.end_s)]
    assert times_s == sorted(times_s) and times_s[0] >= 0.0 and times_s[-1] <= duration_s + 0.01


@needs_goforward
def test_streamed_utterances_decode_well_from_the_first_one_on() -> None:
    """The first utterance is decoded whole, and seeds the running CMN of those streamed after it."""
    recogniser = PocketsphinxRecognizer()
    pcm = GOFORWARD_RAW.read_bytes()[8320:]  # as a VAD forwards it: 250 ms of pre-roll before the onset
    texts = []
    for _ in range(3):
        recogniser.start()
        for offset in range(0, len(pcm), 640):
            recogniser.feed(pcm[offset:offset + 640])
        texts.append(recogniser.finish()[0].text)
    assert texts == ["go forward ten meters"] * 3


@needs_goforward
def test_recognise_is_independent_of_earlier_streaming() -> None:
    recogniser = PocketsphinxRecognizer()
    pcm = GOFORWARD_RAW.read_bytes()
    recogniser.start()
    for offset in range(0, len(pcm), 640):  # 20 ms chunks switch pocketsphinx to running CMN
        recogniser.feed(pcm[offset:offset + 640])
    recogniser.finish()
    assert recogniser.recognise(pcm)[0].text == "go forward ten meters"


def test_every_grammar_word_has_a_pronunciation() -> None:
    sentences = grammar_sentences()
    assert len(sentences) == 50
    missing = {word for sentence in sentences for word in sentence.split()} - known_words()
    assert not missing


@needs_questions
def test_grammar_covers_all_questions() -> None:
    questions = read_questions(QUESTIONS_TSV)
    assert len(questions) == 50
    normalised = [normalise_sentence(question) for _, question in questions]
    assert normalised == grammar_sentences()
    missing = {word for sentence in normalised for word in sentence.split()} - known_words()
    assert not missing


@needs_flite
@needs_questions
def test_generated_files_are_up_to_date(tmp_path: Path) -> None:
    from esiaf_services.asr.tools.make_robocup_grammar import generate

    generate(QUESTIONS_TSV, tmp_path / "robocup.gram", tmp_path / "project.dict")
    assert (tmp_path / "project.dict").read_text() == PROJECT_DICT.read_text()
    assert (tmp_path / "robocup.gram").read_text() == ROBOCUP_GRAMMAR.read_text()


@needs_flite
@pytest.mark.parametrize("question", SPOKEN_QUESTIONS)
def test_synthesised_question_decodes_exactly(question: str, grammar_recogniser: PocketsphinxRecognizer,
                                              synthesiser: ModuleType) -> None:
    pcm = synthesiser.synthesise_sentence(question, "slt").tobytes()
    hypotheses = grammar_recogniser.recognise(pcm)
    assert hypotheses[0].text == normalise_sentence(question)
    assert " ".join(word.word for word in hypotheses[0].words) == hypotheses[0].text


@needs_flite
@pytest.mark.parametrize("voice", ["slt", "awb"])
def test_the_phone_loop_keeps_a_question_and_rejects_speech_out_of_the_grammar(voice: str,
                                                                             synthesiser: ModuleType) -> None:
    """With the phone loop, the best sentence carries its confidence: a question's is well above the
    default; a sentence out of the set, forced onto a question by the grammar search ("where is canada's
    only desert"), falls below it."""
    recogniser = PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR, phone_loop=True)
    (question, *_) = recogniser.recognise(synthesiser.synthesise_sentence("What does CAPTCHA stands for?",
                                                                          voice).tobytes())
    assert question.text == "what does captcha stands for"
    assert question.whole and question.confidence is not None and question.confidence > MIN_CONFIDENCE + 1
    (outside, *_) = recogniser.recognise(synthesiser.synthesise_sentence("Where is the nearest train station?",
                                                                         voice).tobytes())
    assert outside.text.startswith("where is canada's")  # the grammar's nearest
    assert outside.confidence is not None and outside.confidence < MIN_CONFIDENCE


@needs_flite
def test_a_sentence_is_scored_alone_against_the_phone_loop(synthesiser: ModuleType) -> None:
    """``sentence_confidence``: the utterance decoded with a grammar of one sentence. The question said
    gets a confidence as high as the grammar search's; an answer repeating a question's words has no path
    through that question's words to its end (None); the grammar search goes on as before afterwards."""
    recogniser = PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR, phone_loop=True)
    question = synthesiser.synthesise_sentence("What does CAPTCHA stands for?", "slt").tobytes()
    answer = synthesiser.synthesise_sentence("The longest street in the world is Yonge Street.", "slt").tobytes()
    agreed = recogniser.sentence_confidence(question, "what does captcha stands for")
    assert agreed is not None and agreed > MIN_CONFIDENCE + 1
    assert recogniser.sentence_confidence(answer, "what's the longest street in the world") is None
    assert recogniser.recognise(question)[0].text == "what does captcha stands for"
    with pytest.raises(RecognizerError, match="needs a grammar and the phone loop"):
        PocketsphinxRecognizer(grammar=ROBOCUP_GRAMMAR).sentence_confidence(question, "what does captcha stands for")


def test_without_the_phone_loop_there_is_no_confidence(grammar_recogniser: PocketsphinxRecognizer) -> None:
    pcm = GOFORWARD_RAW.read_bytes() if GOFORWARD_RAW.is_file() else b"\0\0" * 16000
    assert all(h.confidence is None and h.word_confidence is None for h in grammar_recogniser.recognise(pcm))


@needs_flite
def test_streamed_chunks_of_any_size_decode(grammar_recogniser: PocketsphinxRecognizer,
                                            synthesiser: ModuleType) -> None:
    pcm = synthesiser.synthesise_sentence(SPOKEN_QUESTIONS[0], "kal16").tobytes()
    grammar_recogniser.start()
    for offset in range(0, len(pcm), 641):  # odd sizes split samples between chunks
        grammar_recogniser.feed(pcm[offset:offset + 641])
    assert grammar_recogniser.finish()[0].text == "how big is the rcmp"


@needs_flite
def test_nbest_probabilities_are_sorted_and_bounded(language_model_recogniser: PocketsphinxRecognizer,
                                                    synthesiser: ModuleType) -> None:
    pcm = synthesiser.synthesise_sentence("go forward ten meters", "slt").tobytes()
    hypotheses = language_model_recogniser.recognise(pcm)
    assert 1 < len(hypotheses) <= language_model_recogniser.nbest
    probabilities = [hypothesis.probability for hypothesis in hypotheses]
    assert probabilities == sorted(probabilities, reverse=True)
    assert all(0.0 <= probability <= 1.0 for probability in probabilities)
    assert sum(probabilities) == pytest.approx(1.0)
    assert len({hypothesis.text for hypothesis in hypotheses}) == len(hypotheses)


def test_silence_gives_no_hypothesis(grammar_recogniser: PocketsphinxRecognizer) -> None:
    assert grammar_recogniser.recognise(b"") == []


@pytest.mark.parametrize("name, text, complaint", [
    ("broken", "#JSGF V1.0;\ngrammar broken;\npublic <q> = hello | ( world ;\n", r"broken\.gram.*syntax error"),
    ("plain", "hello world\n", r"plain\.gram"),
    ("unknown", "#JSGF V1.0;\ngrammar unknown;\npublic <q> = hello xyzzyq ;\n", r"unknown\.gram.*xyzzyq"),
], ids=["malformed", "no header", "word not in dictionary"])
def test_bad_grammar_is_refused_naming_the_file(tmp_path: Path, name: str, text: str, complaint: str) -> None:
    grammar = tmp_path / f"{name}.gram"
    grammar.write_text(text)
    with pytest.raises(RecognizerError, match=complaint):
        PocketsphinxRecognizer(grammar=grammar)


def test_missing_grammar_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecognizerError, match=re.escape(str(tmp_path / "absent.gram"))):
        PocketsphinxRecognizer(grammar=tmp_path / "absent.gram")


def test_bad_dictionary_word_is_refused(tmp_path: Path) -> None:
    dictionary = tmp_path / "bad.dict"
    dictionary.write_text("robot R OW B AA T\nzorgle Z AO R G QX L\n")
    with pytest.raises(RecognizerError, match=r"bad\.dict:2.*zorgle"):
        PocketsphinxRecognizer(extra_dictionary=dictionary)


def test_missing_dictionary_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecognizerError, match=r"absent\.dict"):
        PocketsphinxRecognizer(extra_dictionary=tmp_path / "absent.dict")


def test_unsupported_sample_rate_is_refused() -> None:
    with pytest.raises(RecognizerError, match="8000 Hz"):
        PocketsphinxRecognizer(sample_rate_hz=8000)


def test_feed_without_start_is_refused(grammar_recogniser: PocketsphinxRecognizer) -> None:
    with pytest.raises(RecognizerError, match="start"):
        grammar_recogniser.feed(b"\x00\x00")


def test_example_recording_matches_its_truth(grammar_recogniser: PocketsphinxRecognizer) -> None:
    truth = json.loads((REPO_ROOT / "examples" / "robocup_questions.json").read_text())
    with wave.open(str(REPO_ROOT / "examples" / truth["wav"]), "rb") as reader:
        assert reader.getframerate() == truth["sample_rate_hz"] == 16000
        pcm = reader.readframes(reader.getnframes())
    margin_s = 0.3
    for sentence in truth["sentences"]:
        first = round((sentence["start_s"] - margin_s) * 16000) * 2
        last = round((sentence["end_s"] + margin_s) * 16000) * 2
        assert grammar_recogniser.recognise(pcm[first:last])[0].text == normalise_sentence(sentence["text"])

"""The search for a grammar's sentence nearest a transcript (snapping.py): the same answer as comparing
with every sentence where they can be listed, the GPSR commands' grammar (~10^5 sentences) searched
without listing them, and grammars it cannot search refused with one clear line."""
import itertools
import random
import time

import pytest

from esiaf.tools.gpsr import generate, load
from esiaf.tools.testing import shared_data
from esiaf_services.asr.matching import GrammarError, expand_jsgf
from esiaf_services.asr.snapping import GAP, LEFT_OUT, GrammarSnapper, substitution

SMALL = """#JSGF V1.0;
grammar small;
public <command> = (bring | give) me the <object> [from the <place>] | <NULL> find <who> in the <place>;
<object> = coke | orange juice | cup | cascade pod;
<place> = kitchen | living room | side table;
<who> = robert | robin | a person;
"""


def brute_force(sentences: list[str], transcript: str) -> float:
    """The least edit cost (snapping's costs) from ``transcript`` to any of ``sentences``, each compared."""
    heard = transcript.split()
    best = float("inf")
    for sentence in sentences:
        said = sentence.split()
        row = [j * GAP for j in range(len(heard) + 1)]
        for word in said:
            new = [row[0] + LEFT_OUT]
            for j, other in enumerate(heard, 1):
                new.append(min(row[j] + LEFT_OUT, new[j - 1] + GAP, row[j - 1] + substitution(word, other)))
            row = new
        best = min(best, row[-1])
    return best


def test_the_search_finds_the_nearest_sentence_as_comparing_with_each_does():
    snapper = GrammarSnapper.from_jsgf(SMALL)
    sentences = expand_jsgf(SMALL)
    vocabulary = sorted({w for s in sentences for w in s.split()} | {"cock", "roberts", "living", "the", "uh"})
    rng = random.Random(4)
    for _ in range(200):
        transcript = " ".join(rng.choice(vocabulary) for _ in range(rng.randint(1, 9)))
        snapped = snapper.nearest(transcript)
        assert snapped.sentence in sentences
        assert snapped.cost == pytest.approx(brute_force(sentences, transcript)), transcript
        assert brute_force([snapped.sentence], transcript) == pytest.approx(snapped.cost)


@pytest.mark.parametrize(("transcript", "sentence"), [
    ("Bring me the Coke from the kitchen.", "bring me the coke from the kitchen"),  # the sentence itself
    ("Give me the cock", "give me the coke"),  # a word misheard
    ("Find Roberts in the living room, thank you.", "find robert in the living room"),  # a tail put in
    ("find robin in the", "find robin in the kitchen"),  # cut short
])
def test_a_transcript_snaps_to_the_sentence_it_nearly_is(transcript, sentence):
    snapped = GrammarSnapper.from_jsgf(SMALL).nearest(transcript)
    assert snapped.sentence == sentence
    assert snapped.distance < 0.5


def test_nothing_heard_is_no_sentence():
    assert GrammarSnapper.from_jsgf(SMALL).nearest(" ... ").sentence == ""


def test_the_gpsr_commands_are_searched_without_listing_them(tmp_path):
    grammar = load(shared_data("robocup/Category1Grammar.txt").parent, 1)
    jsgf = grammar.jsgf()
    with pytest.raises(GrammarError, match="more than"):
        expand_jsgf(jsgf)  # too many for a closed set
    snapper = GrammarSnapper.from_jsgf(jsgf)
    commands = generate(grammar, 30, seed=5)
    started = time.process_time()
    for command in commands:
        assert snapper.nearest(command.text).sentence == command.words  # a command is its own nearest
    assert (time.process_time() - started) / len(commands) < 0.5  # ~30 ms each unloaded
    rng = random.Random(2)
    for command in commands:  # two words changed: the nearest is a command, at most that far
        words = command.words.split()
        for i in rng.sample(range(len(words)), 2):
            words[i] = "uh"
        snapped = snapper.nearest(" ".join(words))
        assert grammar.matches(snapped.sentence) and snapped.cost <= 2 * GAP


@pytest.mark.parametrize(("jsgf", "complaint"), [
    ("#JSGF V1.0; grammar g; <a> = hello;", "no public rule"),
    ("#JSGF V1.0; grammar g; public <a> = hello <a>;", "refers to itself"),
    ("#JSGF V1.0; grammar g; public <a> = hello <b>;", "not defined"),
    ("#JSGF V1.0; grammar g; public <a> = hello+;", "repetition"),
    ("#JSGF V1.0; grammar g; public <a> = (hello;", "unbalanced"),
])
def test_a_grammar_it_cannot_search_is_one_clear_error(jsgf, complaint):
    with pytest.raises(GrammarError, match=complaint):
        GrammarSnapper.from_jsgf(jsgf)


def test_a_grammar_past_the_cap_is_refused_not_searched_for_ever():
    levels = "\n".join(f"<l{i}> = <l{i + 1}> <l{i + 1}> | x;" for i in range(30))
    with pytest.raises(GrammarError, match="searched"):
        GrammarSnapper.from_jsgf(f"#JSGF V1.0; grammar g; public <l0> = <l1>;\n{levels}\n<l30> = y;")


def test_letters_make_a_near_word_cheaper_than_another():
    assert substitution("robert", "robert") == 0
    assert substitution("robin", "robert") < substitution("linda", "robert") <= 1
    assert all(0 <= substitution(a, b) <= 1 for a, b in itertools.product(["a", "bed", "dishwasher"], repeat=2))

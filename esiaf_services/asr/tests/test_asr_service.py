"""The asr service's handling of utterances: decoded whole, and skipped when it joined one late
(started or restarted mid-utterance: the end alone would be decoded into a wrong sentence)."""
import importlib.util
import json
import shutil
import sys

import pytest
import soundfile

from esiaf import Audio, AudioFormat
from esiaf.tools.testing import REPO, normalise
from esiaf_services.asr.recognizer import MIN_CONFIDENCE, SECOND_OPINION_MIN_CONFIDENCE
from esiaf_services.asr.service import Asr, AsrSettings

EXAMPLE = REPO / "examples" / "robocup_questions.wav"
NS = 1_000_000_000
RATE = 16000


@pytest.fixture(scope="module", params=["pocketsphinx", "whisper"])
def asr(request):
    if request.param == "whisper":
        pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    component = Asr(AsrSettings(grammar="robocup", backend=request.param))
    component.setup()
    return component


def play(asr, first_s: float, sentence: dict) -> list[tuple]:
    """Feeds the example from ``first_s`` to 0.3 s after the sentence in 20 ms chunks, the last one
    closing the VAD segment (the sentence's speech span); returns what the component emitted."""
    samples, rate = soundfile.read(str(EXAMPLE), dtype="int16")
    assert rate == RATE
    emitted = []
    asr.emit = lambda kind, span, stream_id=None, **payload: (  # partials: not what these tests look at
        None if kind == "partial" else emitted.append((kind, span, payload)))
    fmt = AudioFormat(RATE, "int16", channels=1)
    first, last = int(first_s * RATE), int((sentence["end_s"] + 0.3) * RATE)
    segment = (int(sentence["start_s"] * NS), int(sentence["end_s"] * NS))
    for start in range(first, last, 320):
        chunk = samples[start:min(start + 320, last)]
        audio = Audio(topic="vad/speech", stream_id="late", publisher="vad", sequence=1, start_ns=start * NS // RATE,
                      end_ns=(start + len(chunk)) * NS // RATE, format=fmt, payload=chunk.tobytes())
        if start + 320 >= last:
            audio.meta.segmentation_ended = True
            audio.meta.segment.start_ns, audio.meta.segment.end_ns = segment
        asr.on_audio(audio)
        if audio.meta.segmentation_ended:
            asr.on_segment_end(audio)
    return emitted


def test_an_utterance_heard_from_its_start_is_recognised_and_one_joined_late_is_nothing(asr):
    sentence = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"][1]  # what does captcha stands for
    whole = play(asr, sentence["start_s"] - 0.25, sentence)
    assert len(whole) == 1 and normalise(whole[0][2]["speech"]["hypotheses"][0].text) == \
        normalise(sentence["text"])
    late = play(asr, sentence["start_s"] + 0.6, sentence)  # restarted 0.6 s into it
    assert len(late) == 1 and "joined the utterance 600 ms after its start" in late[0][2]["nothing"]
    assert late[0][1] == (int(sentence["start_s"] * NS), int(sentence["end_s"] * NS))
    again = play(asr, sentence["start_s"] - 0.25, sentence)  # the next utterance is heard whole again
    assert normalise(again[0][2]["speech"]["hypotheses"][0].text) == normalise(sentence["text"])


def feed(asr, samples, stream_id: str) -> list[tuple]:
    """``samples`` as one VAD segment in 20 ms chunks; what the component emitted."""
    return feed_topics(asr, {"vad/speech": samples}, stream_id)


def feed_topics(asr, topics: dict, stream_id: str, until: dict | None = None) -> list[tuple]:
    """One VAD segment on each of ``topics`` (topic: samples, all as long), in 20 ms chunks at the same capture
    times, chunk by chunk in the order given (the vad's before the denoiser's, as the denoiser passes it on);
    a topic the component does not subscribe to never comes, and one in ``until`` stops at that sample; what
    the component emitted."""
    emitted = []
    asr.emit = lambda kind, span, stream_id=None, **payload: (  # partials: not what these tests look at
        None if kind == "partial" else emitted.append((kind, span, payload)))
    fmt = AudioFormat(RATE, "int16", channels=1)
    length = len(next(iter(topics.values())))
    for start in range(0, length, 320):
        for topic, samples in topics.items():
            if topic not in asr.inputs or start >= (until or {}).get(topic, length):
                continue
            chunk = samples[start:start + 320]
            audio = Audio(topic=topic, stream_id=stream_id, publisher=topic.split("/")[0], sequence=start // 320 + 1,
                          start_ns=start * NS // RATE, end_ns=(start + len(chunk)) * NS // RATE, format=fmt,
                          payload=chunk.tobytes())
            if start + 320 >= length:
                audio.meta.segmentation_ended = True
                audio.meta.segment.start_ns, audio.meta.segment.end_ns = 0, length * NS // RATE
            asr.on_audio(audio)
            if audio.meta.segmentation_ended:
                asr.on_segment_end(audio)
    return emitted


@pytest.mark.parametrize("unrecognised", [True, False])
@pytest.mark.parametrize("backend", ["pocketsphinx", "whisper"])
def test_speech_the_recogniser_cannot_make_out_is_reported_as_not_understood(unrecognised, backend):
    """A segment the grammar cannot decode (here 1.5 s of noise) is speech with one empty hypothesis,
    so its fused result still carries direction, emotion and voice; or, if so set, "nothing". Whisper
    (its closed-set decoding): the same, or "nothing" for what its no-speech rule takes for noise."""
    import numpy as np
    if backend == "whisper":
        pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    component = Asr(AsrSettings(grammar="robocup", unrecognised=unrecognised, backend=backend))
    component.setup()
    noise = np.random.default_rng(0).normal(0, 3000, 24000).astype(np.int16)
    emitted = feed(component, noise, "noise")
    assert len(emitted) == 1 and emitted[0][1] == (0, 24000 * NS // RATE)
    if backend == "whisper" and "no speech" in emitted[0][2].get("nothing", ""):
        return
    if unrecognised:
        (best,) = emitted[0][2]["speech"]["hypotheses"]
        assert (best.text, best.raw_text, best.probability, best.out_of_set) == ("", "", 0.0, True)
    else:
        assert emitted[0][2]["nothing"] == "no words recognised"


@pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
@pytest.mark.parametrize("min_confidence", [MIN_CONFIDENCE, None])
def test_pocketsphinx_says_out_of_set_for_speech_none_of_its_sentences(min_confidence):
    """pocketsphinx's grammar search ends on some sentence whatever is said; the phone loop (the default
    with a grammar) rejects one that explains the speech far worse, published as the Whisper path does:
    empty text, out of set, the sentence as raw text. A question is kept. ``min_confidence`` null: no
    phone loop, the sentence is taken."""
    synthesise = synthesiser().synthesise_sentence
    component = Asr(AsrSettings(grammar="robocup", pocketsphinx={"min_confidence": min_confidence}))
    component.setup()
    (question,) = feed(component, synthesise("What does CAPTCHA stands for?", "slt"), "robot")
    assert question[2]["speech"]["hypotheses"][0].text == "what does captcha stands for"
    assert not question[2]["speech"]["hypotheses"][0].out_of_set
    (outside,) = feed(component, synthesise("Where is the nearest train station?", "slt"), "robot")
    best = outside[2]["speech"]["hypotheses"][0]
    if min_confidence is None:
        assert (best.text, best.out_of_set) == ("where is canada's only desert", False)
    else:
        assert (best.text, best.raw_text, best.out_of_set) == ("", "where is canada's only desert", True)


def synthesiser():
    """scripts/synth_questions.py (flite), imported."""
    spec = importlib.util.spec_from_file_location("synth_questions", REPO / "scripts" / "synth_questions.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_past_max_streams_no_utterance_loses_its_decoder_and_idle_decoders_are_reused():
    """Three streams speak at once with ``max_streams`` 2: each keeps its decoder to the end of its
    utterance (none is dropped mid-utterance, which lost it) and all three are recognised; a
    fourth stream, later, takes the decoder of the least recently heard idle one instead of a new one."""
    component = Asr(AsrSettings(grammar="robocup", max_streams=2))
    component.setup()
    made = []
    new_decoder = component._new_decoder
    component._new_decoder = lambda: made.append(1) or new_decoder()
    samples, _ = soundfile.read(str(EXAMPLE), dtype="int16")
    sentences = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"][:3]
    clips = {f"robot{i}": samples[int((s["start_s"] - 0.25) * RATE):int((s["end_s"] + 0.3) * RATE)]
             for i, s in enumerate(sentences)}
    emitted = []
    component.emit = lambda kind, span, stream_id=None, **payload: (  # partials: not what these tests look at
        None if kind == "partial" else emitted.append((stream_id, payload)))
    fmt = AudioFormat(RATE, "int16", channels=1)
    for start in range(0, max(len(c) for c in clips.values()), 320):  # chunk by chunk, in turn
        for stream_id, clip in clips.items():
            chunk = clip[start:start + 320]
            if not len(chunk):
                continue
            audio = Audio(topic="vad/speech", stream_id=stream_id, publisher="vad", sequence=1,
                          start_ns=start * NS // RATE, end_ns=(start + len(chunk)) * NS // RATE, format=fmt,
                          payload=chunk.tobytes())
            if start + 320 >= len(clip):
                audio.meta.segmentation_ended = True
                audio.meta.segment.start_ns, audio.meta.segment.end_ns = 0, len(clip) * NS // RATE
            component.on_audio(audio)
            if audio.meta.segmentation_ended:
                component.on_segment_end(audio)
    heard = {stream_id: normalise(payload["speech"]["hypotheses"][0].text) for stream_id, payload in emitted}
    assert heard == {f"robot{i}": normalise(s["text"]) for i, s in enumerate(sentences)}
    assert len(made) == 2  # robot1 and robot2 (robot0's was made at start-up); the cap passed, none dropped
    assert feed(component, clips["robot0"], "robot3")[0][2]["speech"]["hypotheses"]  # a fourth, later
    assert len(made) == 2 and len(component.streams) == 3  # it took an idle stream's decoder


def test_an_utterance_broken_off_by_a_restarted_vad_is_nothing_and_never_the_next_ones_text():
    """The vad dies in the middle of a question and a new one (another publisher) forwards the next: the
    open utterance is said nothing about, with the reason, and the next is decoded on its own. Decoding
    them together put the first question's words on the second one's span."""
    sentences = json.loads(EXAMPLE.with_suffix(".json").read_text())["sentences"]
    first, second = sentences[0], sentences[1]
    component = Asr(AsrSettings(grammar="robocup"))
    component.setup()
    samples, _ = soundfile.read(str(EXAMPLE), dtype="int16")
    emitted = []
    component.emit = lambda kind, span, stream_id=None, **payload: (  # partials: not what these tests look at
        None if kind == "partial" else emitted.append((kind, span, payload)))
    fmt = AudioFormat(RATE, "int16", channels=1)

    def forward(publisher: str, first_s: float, last_s: float, segment: tuple[float, float] | None) -> None:
        first_n, last_n = int(first_s * RATE), int(last_s * RATE)
        for sequence, start in enumerate(range(first_n, last_n, 320), start=1):
            chunk = samples[start:min(start + 320, last_n)]
            audio = Audio(topic="vad/speech", stream_id="s", publisher=publisher, sequence=sequence,
                          start_ns=start * NS // RATE, end_ns=(start + len(chunk)) * NS // RATE, format=fmt,
                          payload=chunk.tobytes())
            if segment is not None and start + 320 >= last_n:
                audio.meta.segmentation_ended = True
                audio.meta.segment.start_ns, audio.meta.segment.end_ns = (round(t * NS) for t in segment)
            component.on_audio(audio)
            if audio.meta.segmentation_ended:
                component.on_segment_end(audio)

    killed_s = (first["start_s"] + first["end_s"]) / 2
    forward("vad-old", first["start_s"] - 0.25, killed_s, None)  # its end never comes
    forward("vad-new", second["start_s"] - 0.25, second["end_s"] + 0.3, (second["start_s"], second["end_s"]))
    broken, answer = emitted
    assert broken[1] == (int((first["start_s"] - 0.25) * RATE) * NS // RATE, int(killed_s * RATE) * NS // RATE)
    assert "utterance broken off: its VAD went away" in broken[2]["nothing"]
    assert answer[1] == (round(second["start_s"] * NS), round(second["end_s"] * NS))
    assert normalise(answer[2]["speech"]["hypotheses"][0].text) == normalise(second["text"])


@pytest.mark.parametrize("value", ["0", "17", "wide"])
def test_a_bad_scoring_beam_is_one_clear_line(value):
    from esiaf.settings import SettingsError, load_settings
    whisper = {"ESIAF_ASR_BACKEND": "whisper"}
    with pytest.raises(SettingsError, match=r"^bad asr settings \(from environment\): whisper.scoring_beam_size: "):
        load_settings(AsrSettings, "asr", env={**whisper, "ESIAF_ASR_WHISPER__SCORING_BEAM_SIZE": value})
    assert load_settings(AsrSettings, "asr", env={**whisper, "ESIAF_ASR_WHISPER__SCORING_BEAM_SIZE": "3"}
                         ).whisper.scoring_beam_size == 3


@pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
def test_what_pocketsphinx_rejects_whisper_answers_as_second_opinion():
    """``second_opinion: whisper``: where pocketsphinx says out of set, Whisper's scoring of the grammar's
    sentences on the same audio answers. Here a ``min_confidence`` no sentence reaches makes pocketsphinx
    reject everything: without the second opinion the question is lost, with it Whisper's sentence is
    published (its score and transcript beside it), and speech outside the set stays out of set."""
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    synthesise = synthesiser().synthesise_sentence
    question, outside = synthesise("What does CAPTCHA stands for?", "slt"), synthesise(
        "Where is the nearest train station?", "slt")
    alone = Asr(AsrSettings(grammar="robocup", pocketsphinx={"min_confidence": 5.0}))
    alone.setup()
    (lost,) = feed(alone, question, "robot")
    assert lost[2]["speech"]["hypotheses"][0].out_of_set
    component = Asr(AsrSettings(grammar="robocup", pocketsphinx={"min_confidence": 5.0}, second_opinion="whisper"))
    component.setup()
    (answered,) = feed(component, question, "robot")
    best = answered[2]["speech"]["hypotheses"][0]
    assert (best.text, best.out_of_set) == ("what does captcha stands for", False)
    assert best.raw_text and best.logprob < 0 and best.match_score > 0
    (rejected,) = feed(component, outside, "robot")
    assert all(h.text == "" and h.out_of_set for h in rejected[2]["speech"]["hypotheses"])


@pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
def test_whispers_second_opinion_is_taken_only_where_pocketsphinx_agrees_with_it():
    """An answer repeating its question's words is out of set for pocketsphinx, and Whisper's scoring takes
    it for the question ("The longest street in the world is Yonge Street." as "what's the longest street
    in the world"). Asked about that one sentence, pocketsphinx finds no path through its words to the
    utterance's end: with ``second_opinion_min_confidence`` (the default) the answer stays out of set;
    without (null) Whisper's question is published. A question pocketsphinx rejects (a ``min_confidence``
    no sentence reaches) is still answered by Whisper: pocketsphinx agrees with that sentence."""
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    synthesise = synthesiser().synthesise_sentence
    for voice in ("slt", "kal16"):
        question = synthesise("What does CAPTCHA stands for?", voice)
        answer = synthesise("The longest street in the world is Yonge Street.", voice)
        said = {}
        for check in (SECOND_OPINION_MIN_CONFIDENCE, None):
            component = Asr(AsrSettings(grammar="robocup", pocketsphinx={"min_confidence": 5.0},
                                        second_opinion="whisper", second_opinion_min_confidence=check))
            component.setup()
            said[check] = [feed(component, samples, "robot")[0][2]["speech"]["hypotheses"][0]
                           for samples in (question, answer)]
        assert [(h.text, h.out_of_set) for h in said[None]] == [
            ("what does captcha stands for", False), ("what's the longest street in the world", False)], voice
        checked_question, checked_answer = said[SECOND_OPINION_MIN_CONFIDENCE]
        assert (checked_question.text, checked_question.out_of_set) == ("what does captcha stands for", False)
        assert (checked_answer.text, checked_answer.out_of_set) == ("", True), voice


@pytest.mark.parametrize(("settings", "complaint"), [
    ({"second_opinion": "whisper"}, "second_opinion: whisper needs backend pocketsphinx and a grammar"),
    ({"second_opinion": "whisper", "grammar": "robocup", "backend": "whisper"}, "needs backend pocketsphinx"),
])
def test_a_second_opinion_without_a_grammar_search_is_one_clear_line(settings, complaint):
    from esiaf import SetupError
    with pytest.raises(SetupError, match=complaint):
        Asr(AsrSettings(**settings)).setup()


def test_an_unknown_second_opinion_is_refused_when_the_settings_are_read():
    with pytest.raises(ValueError, match="second_opinion"):
        AsrSettings(second_opinion="vosk")


@pytest.fixture(scope="module")
def gpsr(tmp_path_factory):
    """The GPSR commands' grammar (~10^5 commands: more than a closed set holds) as the eval writes it
    (JSGF and its dictionary), the world's vocabulary, and four commands said by flite."""
    from esiaf.tools.evaluation import gpsr_language, gpsr_vocabulary
    from esiaf.tools.gpsr import generate, load
    from esiaf.tools.testing import shared_data
    grammar = load(shared_data("robocup/Category1Grammar.txt").parent, 1)
    work = tmp_path_factory.mktemp("gpsr")
    gram, dictionary = gpsr_language(grammar, work)
    synthesise = synthesiser().synthesise_sentence
    commands = [(c.words, synthesise(c.text, voice)) for c, voice in
                zip(generate(grammar, 4, seed=9), ("slt", "awb", "rms", "slt"), strict=True)]
    return {"grammar": str(gram), "dictionary": str(dictionary),
            "vocabulary": str(gpsr_vocabulary(grammar, work)), "commands": commands}


@pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
@pytest.mark.parametrize("backend", ["pocketsphinx", "whisper"])
def test_a_grammar_too_large_for_a_closed_set_gets_whisper_transcripts_snapped_to_it(gpsr, backend):
    """GPSR's grammar: pocketsphinx's second opinion (here made to reject everything by a ``min_confidence``
    no sentence reaches) is Whisper's transcript, prompted with the vocabulary, snapped to the nearest
    command; the whisper backend with that grammar snaps its transcript the same way. Speech that is no
    command stays out of set."""
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    settings = {"grammar": gpsr["grammar"], "vocabulary": gpsr["vocabulary"],
                "pocketsphinx": {"extra_dictionary": gpsr["dictionary"], "min_confidence": 5.0}}
    if backend == "pocketsphinx":
        alone = Asr(AsrSettings(**settings))
        alone.setup()
        (lost,) = feed(alone, gpsr["commands"][0][1], "robot")
        assert lost[2]["speech"]["hypotheses"][0].out_of_set  # no second opinion: rejected
        settings["second_opinion"] = "whisper"
    component = Asr(AsrSettings(**settings, backend=backend))
    component.setup()
    assert component.info["second_opinion_scoring" if backend == "pocketsphinx" else "scoring"] == "snap"
    right = 0
    for words, samples in gpsr["commands"]:
        (answered,) = feed(component, samples, "robot")
        best = answered[2]["speech"]["hypotheses"][0]
        assert best.raw_text and not best.out_of_set and 0 < best.match_score <= 1
        right += best.text == words
    assert right >= 3, "clean flite speech of the grammar's own commands"
    outside = synthesiser().synthesise_sentence("What is the capital of Australia?", "slt")
    (rejected,) = feed(component, outside, "robot")
    assert all(h.text == "" and h.out_of_set for h in rejected[2]["speech"]["hypotheses"])


@pytest.mark.skipif(shutil.which("flite") is None, reason="Debian's flite is not installed")
def test_the_second_opinion_hears_its_own_topic_where_pocketsphinx_hears_the_denoiser(gpsr):
    """``second_opinion_topic``: the asr hears ``denoiser/speech`` (here noise in place of the command) and
    Whisper's second opinion the same span of ``vad/speech`` (the command): Whisper's transcript of the
    command is snapped to it. Without it, Whisper hears the noise and the command is lost; with part of the
    span missing on vad/speech, the second opinion falls back to the asr's own input and says so in info (on a
    loaded machine the vad's connection to the asr was seen to drop, its end of stream with it: the input's
    end alone ends a stream)."""
    import numpy as np
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    words, command = gpsr["commands"][0]
    noise = np.random.default_rng(0).normal(0, 300, len(command)).astype(np.int16)
    settings = {"grammar": gpsr["grammar"], "vocabulary": gpsr["vocabulary"], "second_opinion": "whisper",
                "input_topic": "denoiser/speech",
                "pocketsphinx": {"extra_dictionary": gpsr["dictionary"], "min_confidence": 5.0}}
    said = {}
    for topic in ("vad/speech", ""):
        component = Asr(AsrSettings(**settings, second_opinion_topic=topic))
        component.setup()
        (said[topic],) = feed_topics(component, {"vad/speech": command, "denoiser/speech": noise}, "robot")
    best = said["vad/speech"][2]["speech"]["hypotheses"][0]
    assert (best.text, best.out_of_set) == (words, False)
    assert all(h.text == "" and h.out_of_set for h in said[""][2]["speech"]["hypotheses"])
    component = Asr(AsrSettings(**settings, second_opinion_topic="vad/speech"))
    component.setup()
    (partly,) = feed_topics(component, {"vad/speech": command, "denoiser/speech": noise}, "robot",
                            until={"vad/speech": len(command) // 2})
    assert all(h.text == "" and h.out_of_set for h in partly[2]["speech"]["hypotheses"])
    assert component.info["second_opinion_unheard"] == 1
    assert component.stream_inputs() == {"denoiser/speech"}  # a stream ends with the input, lost vad audio or not
    (again,) = feed_topics(component, {"vad/speech": command, "denoiser/speech": noise}, "robot")  # whole again
    assert again[2]["speech"]["hypotheses"][0].text == words


@pytest.mark.parametrize(("denoiser", "env", "topic"), [
    ("auto", {"ESIAF_ASR_SECOND_OPINION": "whisper"}, ""),  # not the default: the asr's input
    ("auto", {"ESIAF_ASR_SECOND_OPINION": "whisper", "ESIAF_ASR_SECOND_OPINION_TOPIC": "vad/speech"}, "vad/speech"),
    ("off", {"ESIAF_ASR_SECOND_OPINION": "whisper", "ESIAF_ASR_SECOND_OPINION_TOPIC": "vad/speech"}, ""),  # its input
    ("auto", {"ESIAF_ASR_SECOND_OPINION_TOPIC": "vad/speech"}, ""),  # no second opinion
])
def test_esiaf_run_waits_for_the_second_opinions_own_subscription_where_one_is_asked_for(
        monkeypatch, denoiser, env, topic):
    """``esiaf run``: the topic the asr's second opinion hears besides its input (so that the launcher waits for
    that subscription too before it plays), only where it differs from the asr's input."""
    import argparse

    from esiaf.tools.cli_start import second_opinion_input, speech_inputs
    for name in ("ESIAF_ASR_SECOND_OPINION", "ESIAF_ASR_SECOND_OPINION_TOPIC", "ESIAF_ASR_BACKEND"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    args = argparse.Namespace(denoiser=denoiser, asr=None)
    assert second_opinion_input(speech_inputs(args, set())) == topic


@pytest.mark.parametrize("interval", ["0", "-300"])
def test_a_partial_interval_of_zero_or_less_is_refused_at_start_up(tmp_path, interval):
    """The asr started with ``partial_interval_ms`` 0 or negative stops before it registers, with one line
    that names the setting and where it came from (exit 2)."""
    import os
    import subprocess
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_ASR_PARTIAL_INTERVAL_MS": interval,
           "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9", "ESIAF_REGISTER_TIMEOUT_S": "0.5"}
    done = subprocess.run([sys.executable, "-m", "esiaf_services.asr"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "partial_interval_ms" in done.stderr and "environment" in done.stderr, done.stderr
    assert "register" not in done.stderr.lower(), done.stderr  # refused before it tried to register


def test_the_second_opinions_audio_is_bounded_whatever_its_stamps_say(monkeypatch):
    """A producer on ``second_opinion_topic`` whose capture stamps run backwards (never older than 120 s than
    the newest) cannot make the asr keep more than ``MAX_HEARD_CHUNKS`` chunks of a stream."""
    from esiaf_services.asr import service
    monkeypatch.setattr(service, "MAX_HEARD_CHUNKS", 500)
    component = Asr(AsrSettings(grammar="robocup", second_opinion="whisper", input_topic="denoiser/speech",
                                second_opinion_topic="vad/speech"))
    fmt = AudioFormat(RATE, "int16", channels=1)
    for n in range(2000):
        start_ns = (10_000 - n) * 1_000_000  # each chunk 1 ms earlier than the one before
        component.on_audio(Audio(topic="vad/speech", stream_id="robot", publisher="vad", sequence=n + 1,
                                 start_ns=start_ns, end_ns=start_ns + 1_000_000, format=fmt, payload=b"\0\0" * 16))
    heard = component.streams["robot"].heard
    assert len(heard) == 500 and heard[-1][0] == (10_000 - 1999) * 1_000_000  # the newest kept

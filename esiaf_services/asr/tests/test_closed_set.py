"""Closed-set decoding by Whisper's acoustic model (closed_set.py) on real speech in real noise:
flite voices over the kitchen noise of the shared data, decoded by Whisper tiny.en."""
import numpy as np
import pytest
import soundfile

from esiaf.tools.testing import REPO, normalise
from esiaf_services.asr.lexicon import ROBOCUP_GRAMMAR
from esiaf_services.asr.matching import GrammarError, SentenceMatcher

KITCHEN = REPO.parent / "shared" / "data" / "noise" / "speech_commands_bg" / "doing_the_dishes.wav"


@pytest.fixture(scope="module")
def decoder():
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf_services.asr.closed_set import ClosedSetDecoder
    from esiaf_services.asr.whisper import WhisperRecognizer
    return ClosedSetDecoder(WhisperRecognizer().model, SentenceMatcher.from_file(ROBOCUP_GRAMMAR, 0.6))


def spoken(text: str, voice: str, snr_db: float | None = None, noise_at_s: float = 0.0) -> np.ndarray:
    """``text`` said by flite's ``voice``, over the kitchen noise at ``snr_db`` (None: clean)."""
    from esiaf.scenes import SceneError, speak
    try:
        speech = speak(text, voice, 16000).astype(np.float32)
    except SceneError as exc:
        pytest.skip(str(exc))
    if snr_db is None:
        return speech
    if not KITCHEN.is_file():
        pytest.skip(f"{KITCHEN} is missing (the shared test data)")
    noise, _ = soundfile.read(str(KITCHEN), dtype="float32")
    noise = noise[int(noise_at_s * 16000):][:len(speech)]
    gain = np.sqrt(np.mean(speech ** 2) / np.mean(noise ** 2) / 10 ** (snr_db / 10))
    return speech + gain * noise


@pytest.mark.parametrize("question, noise_at_s", [
    ("What country holds the record for the most gold medals at the Winter Olympics?", 3.0),
    ("How many tons of snow are required to build The Hotel de Glace?", 6.0),
])
def test_the_audio_picks_the_question_where_the_transcript_is_wrong(decoder, question, noise_at_s):
    """At 0 dB the free transcript is far from the question (its nearest sentence is wrong or out of
    set), and the question is still the sentence the model finds likeliest."""
    result = decoder.decode(spoken(question, "kal16", 0.0, noise_at_s))
    nearest = decoder.matcher.match(result.raw_text)
    assert not (nearest.in_set and normalise(nearest.sentence) == normalise(question)), result.raw_text
    assert normalise(result.ranked[0].sentence) == normalise(question) and result.in_set
    assert result.margin > 0 and len(result.ranked) == decoder.shortlist
    assert result.words and normalise(" ".join(w.word for w in result.words)) == normalise(question)


@pytest.mark.parametrize("said", ["Bring me the coke from the kitchen table.", "What is the capital of France?",
                                  "Good morning, how are you today?"])
def test_speech_outside_the_set_is_rejected(decoder, said):
    result = decoder.decode(spoken(said, "slt"))
    assert not result.in_set, (result.raw_text, result.ranked[0].sentence, result.per_token)


def test_a_question_said_clearly_is_in_the_set_with_its_words_timed(decoder):
    question = "Who invented the compiler?"
    samples = spoken(question, "awb")
    result = decoder.decode(samples)
    assert result.in_set and normalise(result.ranked[0].sentence) == normalise(question)
    assert [normalise(w.word) for w in result.words] == normalise(question).split()
    assert all(0 <= w.start_s <= w.end_s <= len(samples) / 16000 for w in result.words)
    assert decoder.decode(samples[:800]) is None  # 50 ms: too short to decode


def test_a_set_of_more_sentences_than_the_cap_is_one_clear_error(tmp_path):
    """100,000 lines: refused at once with the count (each transcript is compared with every one)."""
    import time
    path = tmp_path / "many.txt"
    path.write_text("".join(f"go to room {n}\n" for n in range(100_000)))
    started = time.monotonic()
    with pytest.raises(GrammarError, match="100000 sentences, more than the 10000"):
        SentenceMatcher.from_file(path, 0.6)
    assert time.monotonic() - started < 30


def test_the_service_reports_the_sentence_its_score_the_transcript_and_the_runner_up():
    """The asr with whisper and a grammar: hypotheses are the shortlist, best first, each with its
    log-probability; the first with the raw transcript, its words and its lead over the runner-up."""
    pytest.importorskip("faster_whisper", reason="the asr-whisper extra is not installed (setup.sh installs it)")
    from esiaf import Audio, AudioFormat
    from esiaf_services.asr.service import Asr, AsrSettings
    asr = Asr(AsrSettings(backend="whisper", grammar="robocup"))
    asr.setup()
    assert asr.info["scoring"] == "acoustic"
    question = "How big is the RCMP?"
    pcm = (np.clip(spoken(question, "slt"), -1, 1) * 32767).astype("<i2")
    emitted: list = []
    asr.emit = lambda kind, span, stream_id=None, **payload: None if kind == "partial" else emitted.append(payload)  # type: ignore[method-assign]
    end_ns = len(pcm) * 1_000_000_000 // 16000
    audio = Audio(topic="vad/speech", stream_id="s", publisher="vad", sequence=1, start_ns=0, end_ns=end_ns,
                  format=AudioFormat(16000, "int16", channels=1), payload=pcm.tobytes())
    audio.meta.segmentation_ended = True
    audio.meta.segment.start_ns, audio.meta.segment.end_ns = 0, end_ns
    asr.on_audio(audio)
    asr.on_segment_end(audio)
    first, second, *_ = emitted[0]["speech"]["hypotheses"]
    assert normalise(first.text) == normalise(question) and not first.out_of_set and first.raw_text
    assert first.logprob < 0 and first.raw_logprob < 0 and first.margin == pytest.approx(first.logprob - second.logprob)
    assert second.text and second.logprob < first.logprob and first.probability > second.probability
    assert first.words and first.words[-1].end_ns <= end_ns


@pytest.mark.parametrize("setting, complaint", [({"scoring": "best"}, "unknown asr scoring 'best'"),
                                                ({"shortlist": 0}, "shortlist must be at least 1")])
def test_bad_scoring_settings_are_one_line(setting, complaint):
    from esiaf import SetupError
    from esiaf_services.asr.service import Asr, AsrSettings
    with pytest.raises(SetupError, match=complaint):
        Asr(AsrSettings(backend="whisper", grammar="robocup", whisper=setting))

"""ASR service: pocketsphinx decodes each VAD segment as it streams in."""
from __future__ import annotations

import logging
from pathlib import Path

from esiaf import Audio, AudioFormat, Component, ComponentSettings, SetupError, hypothesis
from services.asr.recognizer import DEFAULT_EXTRA_DICT, PocketsphinxRecognizer, RecognizerError

log = logging.getLogger(__name__)

GRAMMARS = Path(__file__).resolve().parent / "grammars"


class AsrSettings(ComponentSettings):
    input_topic: str = "vad/speech"
    sample_rate_hz: int = 16000
    grammar: str = ""  # a JSGF file, or the name of a bundled grammar ("robocup"); empty = language model
    extra_dictionary: str = str(DEFAULT_EXTRA_DICT)  # project words on top of the bundled dictionary
    language_weight: float = 7.5
    nbest: int = 5


def resolve_grammar(grammar: str) -> Path | None:
    if not grammar:
        return None
    bundled = GRAMMARS / f"{grammar}.gram"
    return bundled if "/" not in grammar and bundled.is_file() else Path(grammar)


class Asr(Component):
    """Speech recogniser (pocketsphinx, streaming, n-best)."""

    service = "asr"
    designation = "speech"
    Settings = AsrSettings

    options = {"grammar": "JSGF grammar file, or a bundled grammar name (robocup)"}

    def __init__(self, settings: AsrSettings):
        super().__init__(settings)
        self.add_input(settings.input_topic, AudioFormat(settings.sample_rate_hz, "int16", channels=1))
        self.recognizer: PocketsphinxRecognizer | None = None
        self._utterance_start_ns: int | None = None
        self._utterance_stream = ""
        self.utterances = 0

    def setup(self) -> None:
        s = self.settings
        try:
            self.recognizer = PocketsphinxRecognizer(
                sample_rate_hz=s.sample_rate_hz, grammar=resolve_grammar(s.grammar),
                extra_dictionary=s.extra_dictionary or None, language_weight=s.language_weight, nbest=s.nbest)
        except RecognizerError as exc:
            raise SetupError(str(exc)) from None
        self.info["grammar"] = s.grammar or "language model"

    def on_audio(self, audio: Audio) -> None:
        if not audio.payload:
            return
        if self._utterance_start_ns is None:
            self.recognizer.start()
            self._utterance_start_ns = audio.start_ns
            self._utterance_stream = audio.stream_id
        elif audio.stream_id != self._utterance_stream:
            log.warning("audio of stream_id=%s inside an utterance of stream_id=%s; decoding it with it",
                        audio.stream_id, self._utterance_stream)
        self.recognizer.feed(audio.payload)

    def on_segment_end(self, audio: Audio) -> None:
        if self._utterance_start_ns is None:
            return
        origin_ns, self._utterance_start_ns = self._utterance_start_ns, None
        hypotheses = self.recognizer.finish()
        segment = audio.meta.segment
        span = (segment.start_ns, segment.end_ns) if segment.end_ns else (origin_ns, audio.end_ns)
        self.utterances += 1
        self.info["utterances"] = self.utterances
        if not hypotheses:
            self.emit("speech", span, stream_id=audio.stream_id, nothing="no words recognised")
            log.info("utterance stream_id=%s start_ns=%d recognised nothing", audio.stream_id, span[0])
            return
        self.emit("speech", span, stream_id=audio.stream_id, speech={"hypotheses": [
            hypothesis(h.text, h.probability, [
                {"word": w.word, "start_ns": origin_ns + round(w.start_s * 1e9),
                 "end_ns": origin_ns + round(w.end_s * 1e9), "probability": w.probability} for w in h.words])
            for h in hypotheses]})
        log.info("utterance stream_id=%s start_ns=%d text=%r p=%.2f", audio.stream_id, span[0],
                 hypotheses[0].text, hypotheses[0].probability)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        if self._utterance_start_ns is not None and self._utterance_stream == stream_id:
            self.on_segment_end(audio)  # a segment the VAD never closed

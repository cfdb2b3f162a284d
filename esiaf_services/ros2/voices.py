"""What a fused result says on ROS4HRI's voice topics: pure mapping from the orchestrator's JSON to
(ROS topic, message) pairs, and the voices heard lately (no DDS, no sockets).

A voice's id is its ``voice_id`` label (an enrolled name, or the stream's anonymous ``voice-N``), else
the talker's ssl track (``track_<source_id>``), else ``unknown``; made a valid ROS name segment.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from esiaf_services.ros2.messages import (
    FEMALE,
    MALE,
    PERSON,
    UNDEFINED,
    VOICE,
    Bool,
    Expression,
    Header,
    IdsList,
    IdsMatch,
    LiveSpeech,
    SoftBiometrics,
    Time,
    Vector3,
    Vector3Stamped,
)

ANONYMOUS = re.compile(r"^voice-\d+$")  # the voiceid service's names for voices nobody enrolled
GENDERS = {"female": FEMALE, "male": MALE}
Publication = tuple[str, Any]  # (ROS topic name, message)


class Unmappable(ValueError):
    """A fused result (or another websocket message) the bridge cannot map: counted by ``reason``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


def segment(text: str) -> str:
    """``text`` as one ROS name segment: letters, digits and single underscores, not starting with a
    digit, not ending with an underscore (``voice-2`` -> ``voice_2``, ``Zoë B.`` -> ``Zo_B``)."""
    name = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)).strip("_")
    if not name:
        return "unknown"
    return f"v{name}" if name[0].isdigit() else name


def namespace(text: str) -> str:
    """A namespace setting as a prefix: "" or ``/robot1`` (each segment made valid)."""
    parts = [segment(part) for part in text.split("/") if part]
    return "".join(f"/{part}" for part in parts)


@dataclass
class Heard:
    voice_id: str  # the topic segment
    namespace: str
    last_s: float  # monotonic time it was last heard


@dataclass(frozen=True)
class Utterance:
    """A fused utterance's audio to publish: on ``topic``, the stream's samples within the span."""
    topic: str
    stream_id: str
    start_ns: int
    end_ns: int


@dataclass
class Voices:
    """Turns fused results into publications, and keeps which voices were heard lately, per namespace.

    ``prefix``: every topic's namespace ("" or ``/robot1``); ``per_stream``: each stream's topics in a
    namespace of its own below it (``/robot1/<stream>/humans/...``)."""

    prefix: str = ""
    per_stream: bool = False
    language: str = "en-US"
    frame_id: str = "esiaf_array"
    forget_after_s: float = 30.0
    max_voices: int = 64
    heard: dict[tuple[str, str], Heard] = field(default_factory=dict)
    namespaces: set[str] = field(default_factory=set)
    speaking: set[tuple[str, str]] = field(default_factory=set)  # (namespace, voice) said is_speaking=True

    def namespace_of(self, stream_id: str) -> str:
        ns = self.prefix + (f"/{segment(stream_id)}" if self.per_stream else "")
        self.namespaces.add(ns)
        return ns

    def fused(self, message: dict[str, Any], now_s: float) -> list[Publication]:
        """A fused result (any revision): the first revision says the speech (final) and is_speaking;
        every revision says direction, expression, soft biometrics and candidate matches (a late
        analyser's result comes in a later revision)."""
        try:
            stream_id, anchor = message["stream_id"], message["anchor"]
            aggregates, results = message.get("aggregates", {}), message.get("results", {})
            start_ns = int(anchor["span"]["start_ns"])
            revision = int(message.get("revision", 1))
            if not isinstance(stream_id, str) or not isinstance(aggregates, dict) or not isinstance(results, dict):
                raise TypeError("stream_id, aggregates or results of the wrong type")
            ns = self.namespace_of(stream_id)
            voice = self.voice_of(aggregates, results)
            base = f"{ns}/humans/voices/{voice}"
            out: list[Publication] = []
            if revision == 1:
                out += self.speech(base, ns, voice, anchor, start_ns)
            out += self.labels(base, aggregates, start_ns)
            out += self.matches(ns, voice, results)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise Unmappable("bad_fused_result", f"{type(exc).__name__}: {exc}") from None
        self.hear(ns, voice, now_s)
        return out

    def utterance(self, message: dict[str, Any]) -> Utterance | None:
        """Where a fused result's audio goes: the first revision of a recognised utterance, its voice's
        ``audio`` topic and its capture span (None for a later revision, or no speech). Called after
        :meth:`fused` accepted the message."""
        try:
            anchor = message["anchor"]
            if int(message.get("revision", 1)) != 1 or anchor.get("speech") is None:
                return None
            stream_id, span = message["stream_id"], anchor["span"]
            voice = self.voice_of(message.get("aggregates", {}), message.get("results", {}))
            return Utterance(f"{self.namespace_of(stream_id)}/humans/voices/{voice}/audio", stream_id,
                             int(span["start_ns"]), int(span["end_ns"]))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise Unmappable("bad_span", f"{type(exc).__name__}: {exc}") from None

    def partial(self, message: dict[str, Any], now_s: float) -> list[Publication]:
        """A partial result (``{"type": "partial", "stream_id", "span", "text", "closed", ...}``,
        docs/protocol.md): LiveSpeech with ``incremental`` set, and is_speaking True while it goes on,
        on the voice ``unknown`` (nobody is known before the utterance is fused); closed: is_speaking
        False there (the fused result's final speech goes to the voice it names)."""
        try:
            stream_id, text = message["stream_id"], message["text"]
            start_ns = int(message["span"]["start_ns"])
            closed = message.get("closed", False)
            if not isinstance(stream_id, str) or not isinstance(text, str) or not isinstance(closed, bool):
                raise TypeError("stream_id or text is not a string, or closed not a boolean")
        except (KeyError, TypeError, ValueError) as exc:
            raise Unmappable("bad_partial", f"{type(exc).__name__}: {exc}") from None
        ns = self.namespace_of(stream_id)
        voice = segment(str(message.get("voice_id") or "unknown"))
        base = f"{ns}/humans/voices/{voice}"
        out: list[Publication] = []
        if closed:
            if (ns, voice) in self.speaking:
                self.speaking.discard((ns, voice))
                out.append((f"{base}/is_speaking", Bool(False)))
            return out
        if (ns, voice) not in self.speaking:
            self.speaking.add((ns, voice))
            out.append((f"{base}/is_speaking", Bool(True)))
        out.append((f"{base}/speech", LiveSpeech(header=header(start_ns), incremental=text, final="",
                                                 confidence=0.0, language=self.language)))
        self.hear(ns, voice, now_s)
        return out

    def voice_of(self, aggregates: dict[str, Any], results: dict[str, Any]) -> str:
        label = (aggregates.get("voice_id") or {}).get("label")
        if label and label != "unknown":
            return segment(str(label))
        track = (aggregates.get("ssl") or {}).get("source_id")
        return segment(f"track_{track}") if track else "unknown"

    def speech(self, base: str, ns: str, voice: str, anchor: dict[str, Any], start_ns: int) -> list[Publication]:
        """is_speaking True (unless partials said it) and False around the final LiveSpeech: the fused
        result comes once the utterance has ended."""
        out: list[Publication] = []
        if (ns, voice) not in self.speaking:
            out.append((f"{base}/is_speaking", Bool(True)))
        self.speaking.discard((ns, voice))
        speech = anchor.get("speech")
        if speech is not None:
            best: dict[str, Any] = speech["hypotheses"][0] if speech["hypotheses"] else {"text": "", "probability": 0.0}
            text = best["text"] or best.get("raw_text", "")
            if not isinstance(text, str):
                raise TypeError("the hypothesis text is not a string")
            out.append((f"{base}/speech", LiveSpeech(header=header(start_ns), incremental="", final=text,
                                                     confidence=float(best["probability"]),
                                                     language=self.language)))
        out.append((f"{base}/is_speaking", Bool(False)))
        return out

    def labels(self, base: str, aggregates: dict[str, Any], start_ns: int) -> list[Publication]:
        out: list[Publication] = []
        ssl = aggregates.get("ssl")
        if ssl and not ssl.get("background"):
            azimuth, elevation = math.radians(float(ssl["azimuth_deg"])), math.radians(float(ssl["elevation_deg"]))
            vector = Vector3(x=math.cos(elevation) * math.cos(azimuth), y=math.cos(elevation) * math.sin(azimuth),
                             z=math.sin(elevation))
            out.append((f"{base}/direction", Vector3Stamped(header=header(start_ns, self.frame_id), vector=vector)))
        emotion = aggregates.get("emotion")
        if emotion:
            out.append((f"{base}/expression", Expression(header=header(start_ns), expression=str(emotion["label"]),
                                                         valence=0.0, arousal=0.0,
                                                         confidence=float(emotion["probability"]))))
        gender = aggregates.get("gender")
        if gender:
            out.append((f"{base}/softbiometrics", SoftBiometrics(
                header=header(start_ns), age=0, age_confidence=0.0,
                gender=GENDERS.get(str(gender["label"]).lower(), UNDEFINED),
                gender_confidence=float(gender["probability"]))))
        return out

    def matches(self, ns: str, voice: str, results: dict[str, Any]) -> list[Publication]:
        """An anonymous voice and the enrolled voice (a person) it is nearest to, with the cosine score
        the voiceid service gave it (below its threshold: that is why it stayed anonymous)."""
        out: list[Publication] = []
        for result in results.get("voice_id") or []:
            payload = result.get("voice_id") or {}
            label, scores = payload.get("label", ""), payload.get("class_probabilities") or {}
            if not ANONYMOUS.match(str(label)) or segment(str(label)) != voice or not scores:
                continue
            name, score = max(scores.items(), key=lambda item: float(item[1]))
            out.append((f"{ns}/humans/candidate_matches",
                        IdsMatch(id1=voice, id1_type=VOICE, id2=segment(str(name)), id2_type=PERSON,
                                 confidence=min(max(float(score), 0.0), 1.0))))
        return out

    def hear(self, ns: str, voice: str, now_s: float) -> None:
        self.heard[(ns, voice)] = Heard(voice, ns, now_s)
        if len(self.heard) > self.max_voices:  # the least recently heard goes first
            oldest = min(self.heard, key=lambda key: self.heard[key].last_s)
            del self.heard[oldest]

    def tracked(self, now_s: float, now_ns: int) -> list[Publication]:
        """Each namespace's IdsList of the voices heard within ``forget_after_s`` (every namespace
        seen so far, an empty list included: REP-155 republishes it at 1 Hz)."""
        for key in [key for key, heard in self.heard.items() if now_s - heard.last_s > self.forget_after_s]:
            del self.heard[key]
        namespaces = self.namespaces or {self.prefix}
        return [(f"{ns}/humans/voices/tracked",
                 IdsList(header=header(now_ns), ids=sorted(h.voice_id for h in self.heard.values()
                                                           if h.namespace == ns)))
                for ns in sorted(namespaces)]


def header(stamp_ns: int, frame_id: str = "") -> Header:
    return Header(stamp=Time.from_ns(stamp_ns), frame_id=frame_id)

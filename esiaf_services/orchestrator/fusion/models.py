"""What fusion publishes, one model: :class:`FusedResult`. The engine builds it (engine.py), the results
plane serialises it once (planes/ingest.py: the text it stores, serves at ``GET /fused`` and sends on
``/ws/fused``), and the API documents it (``FusedPage``, the OpenAPI document at /docs).

A fused result holds the results it fuses as they were stored: their JSON objects, made and checked by the
results plane's codec when they arrived (planes/codec.py), not parsed again at every publication. The
models below (:class:`Result` and its payloads, the aggregates) describe those objects; they document
them in the OpenAPI document and ``GET /results``. Pure: no I/O.
"""
from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, GetJsonSchemaHandler
from pydantic.json_schema import JsonSchemaValue

# A fused result lists at most this many results of one kind (an ssl frame is 128 ms: 25 s of a talker's
# directions); the aggregates are computed from all of them, and ``omitted`` counts what was left out.
# An analyser that sends thousands of results per utterance would otherwise make every revision, and every
# websocket client's copy of it, megabytes long.
MAX_LISTED_PER_KIND = 200


# a result, as stored and sent (docs/protocol.md); exactly one payload key is present
class Span(BaseModel):
    start_ns: int
    end_ns: int


class VadPayload(BaseModel):
    probability: float


class WordTiming(BaseModel):
    word: str
    start_ns: int
    end_ns: int
    probability: float


class Hypothesis(BaseModel):
    text: str = Field(description="with a closed set: the matched allowed sentence, empty when out of set")
    probability: float
    words: list[WordTiming]
    raw_text: str = Field(default="", description="with a closed set: what the recogniser heard")
    match_score: float = Field(default=0.0, description="with a closed set: 1 - word distance / length")
    out_of_set: bool = Field(default=False, description="with a closed set: no allowed sentence is near enough")
    logprob: float = Field(default=0.0, description="closed set scored by the acoustic model: this sentence's "
                           "log-probability given the audio (nats)")
    raw_logprob: float = Field(default=0.0, description="closed set scored by the acoustic model: raw_text's")
    margin: float = Field(default=0.0, description="closed set scored by the acoustic model: the lead over the "
                          "next hypothesis (the runner-up)")


class SpeechPayload(BaseModel):
    hypotheses: list[Hypothesis] = Field(description="n-best, best first")


class SslDirection(BaseModel):
    source_id: str = Field(description="the tracked source this direction belongs to")
    azimuth_deg: float = Field(description="this frame's, counter-clockwise from the array's x axis")
    elevation_deg: float = Field(description="meaningful only where elevation_known")
    probability: float = Field(description="the localiser's confidence in this direction, 0..1")
    elevation_known: bool = Field(default=False, description="the array can tell elevation (microphones off one "
                                  "plane) and the algorithm searched it")
    track_azimuth_deg: float = Field(default=0.0, description="the tracked source's smoothed azimuth")
    background: bool = Field(default=False, description="the track has stayed in one place far longer than an "
                             "utterance: a loudspeaker, a TV, a dishwasher, not a talker")


class SslPayload(BaseModel):
    directions: list[SslDirection] = Field(description="best first")
    algorithm: str = Field(default="", description='the localiser, e.g. "NormMUSIC"')
    level_db: float = Field(default=0.0, description="the frame's level, 96 dB = full-scale RMS")


class UtteranceQuality(BaseModel):
    """voice_id only: the voiceid's estimate of how fit the segment was to tell a voice by."""
    snr_db: float = Field(description="mean level of its speech frames over its noise floor")
    speech_s: float = Field(description="its first frame of speech to the last")
    reason: str = Field(description="why it is under the voiceid's gate (the label is then 'unknown'); "
                                    "empty: it is not")


class LabelPayload(BaseModel):
    label: str
    probability: float
    class_probabilities: dict[str, float]
    embedding: list[float] = Field(default_factory=list, description="voice_id only: the segment's speaker "
                                   "embedding (unit length), from which a voice can be enrolled")
    quality: UtteranceQuality | None = Field(None, description="voice_id only (all zero for other kinds): the "
                                             "segment's quality; with a reason, the label is 'unknown'")


class NoResultPayload(BaseModel):
    reason: str


class Result(BaseModel):
    model_config = ConfigDict(extra="allow")  # a kind that is not built in: its payload under its name

    id: int
    component: str = Field(description="the service that produced it (its component name)")
    instance: str = Field(default="", description="the instance of it that produced it (its component_id; "
                                                  "empty from an older SDK)")
    type: str = Field(description="the result kind: built in, or any other (its payload then has "
                                   "label, probability, class_probabilities, value, has_value, text, attributes)")
    stream_id: str
    span: Span = Field(description="capture time of the audio the result was computed on")
    produced_ns: int
    received_ns: int
    latency_ms: float = Field(description="(received_ns - span.end_ns) / 1e6, the capture times put on the "
                                          "orchestrator's clock (the capturing component's clock_offset_ms)")
    sequence: int
    vad: VadPayload | None = None
    speech: SpeechPayload | None = None
    ssl: SslPayload | None = None
    emotion: LabelPayload | None = None
    gender: LabelPayload | None = None
    voice_id: LabelPayload | None = None
    nothing: NoResultPayload | None = Field(default=None, description="covered, no result")


class SslAggregate(BaseModel):
    azimuth_deg: float = Field(description="the talker's track: circular mean of its directions, weighted by "
                               "overlap x probability")
    elevation_deg: float
    concentration: float = Field(description="mean resultant length: 1 all agree, 0 cancel out")
    overlap_s: float = Field(description="capture time of the window the results cover")
    directions: int = Field(description="directions of the talker's track within the window")
    source_id: str = Field(default="", description="the talker's track: the heaviest one not marked background")
    background: bool = Field(default=False, description="every track heard was background")
    tracks: int = Field(default=1, description="tracked sources heard within the window")


class LabelAggregate(BaseModel):
    label: str = Field(description="the top label")
    probability: float = Field(description="its share of the distribution")
    distribution: dict[str, float] = Field(description="overlap-weighted, sums to 1, top first")
    overlap_s: float


class GenericAggregate(BaseModel):
    label: str | None = Field(default=None, description="the top label, where the results have labels")
    probability: float | None = None
    distribution: dict[str, float] | None = None
    value: float | None = Field(default=None, description="overlap-weighted mean, where the results have values")
    overlap_s: float


MissingReason = Literal["timed_out", "gone", "skipped"]
Completion = Literal["complete", "timed_out", "components_gone"]


class Missing(BaseModel):
    component: str
    type: str
    reason: MissingReason


class DocumentedAs:
    """Metadata of a field that holds a plain JSON value (a dict) which ``models`` describe: its JSON
    schema is theirs, while the value is neither parsed into them nor serialised by them."""

    def __init__(self, *models: type[BaseModel], nullable: bool = False) -> None:
        self.models, self.nullable = models, nullable

    def __get_pydantic_json_schema__(self, core_schema: Any, handler: GetJsonSchemaHandler) -> JsonSchemaValue:
        schemas = [handler(model.__pydantic_core_schema__) for model in self.models]
        if self.nullable:
            schemas.append({"type": "null"})
        return schemas[0] if len(schemas) == 1 else {"anyOf": schemas}


# a result's JSON object as stored (a dict), documented as a Result
ResultJson = Annotated[dict[str, Any], DocumentedAs(Result)]
# an aggregate as aggregate.py makes it: a dict, or None for a type without results
AggregateJson = Annotated[dict[str, Any] | None, DocumentedAs(SslAggregate, LabelAggregate, GenericAggregate,
                                                                    nullable=True)]


class FusedResult(BaseModel):
    """One publication of a fusion (docs/protocol.md, "Fused results")."""

    type: Literal["fused_result"] = "fused_result"
    id: int = Field(description="stable across revisions")
    revision: int = Field(description="1 for the first publication")
    fusion: str
    stream_id: str
    anchor: ResultJson = Field(description="its span is the window")
    results: dict[str, list[ResultJson]] = Field(
        description="every fused type: its results overlapping the window, by start")
    aggregates: dict[str, AggregateJson] = Field(
        description="ssl, label kinds and every kind that is not built in: null when they have no results")
    completion: Completion = Field(
        description="how revision 1 was decided; kept in later revisions")
    missing_components: list[str] = Field(description="components that had not covered the window")
    missing: list[Missing]
    published_ns: int
    playback_overlap: float = Field(default=0.0, description="the share of the window its stream's robot was "
                                    "playing (its player's playback results), 0..1")
    source: Literal["person", "robot"] = Field(default="person", description='"robot": the robot\'s own voice '
                                               "heard back (fusion/playback.py's rule); left out of GET /fused, "
                                               "/ws/fused and esiaf run unless include_robot=true")
    seq: int = Field(default=0, description="publication number: every revision has its own, increasing; "
                                            "resume the websocket with after_seq")
    omitted: dict[str, int] = Field(default_factory=dict, description=(
        f"kinds with more than {MAX_LISTED_PER_KIND} results in the window: how many were left out of "
        "`results` (evenly over the window; the aggregates count every one)"))

    def to_json(self) -> str:
        """The text that is stored and sent (compact; integers stay integers; NaN is refused)."""
        return json.dumps(self.model_dump(), separators=(",", ":"), allow_nan=False)


def bounded_lists(results: dict[str, list[dict[str, Any]]],
                  limit: int = MAX_LISTED_PER_KIND) -> tuple[dict[str, list[dict[str, Any]]], dict[str, int]]:
    """``results`` with at most ``limit`` per kind, kept evenly over each list (its first and last among
    them, in order), and how many of each kind were left out (only kinds that lost some)."""
    bounded, omitted = {}, {}
    for kind, items in results.items():
        if len(items) <= limit:
            bounded[kind] = items
            continue
        step = (len(items) - 1) / (limit - 1)
        bounded[kind] = [items[round(i * step)] for i in range(limit)]
        omitted[kind] = len(items) - limit
    return bounded, omitted

from google.protobuf import struct_pb2 as _struct_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class SampleType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SAMPLE_TYPE_UNSPECIFIED: _ClassVar[SampleType]
    SAMPLE_TYPE_INT8: _ClassVar[SampleType]
    SAMPLE_TYPE_UINT8: _ClassVar[SampleType]
    SAMPLE_TYPE_INT16: _ClassVar[SampleType]
    SAMPLE_TYPE_UINT16: _ClassVar[SampleType]
    SAMPLE_TYPE_INT24: _ClassVar[SampleType]
    SAMPLE_TYPE_UINT24: _ClassVar[SampleType]
    SAMPLE_TYPE_INT32: _ClassVar[SampleType]
    SAMPLE_TYPE_UINT32: _ClassVar[SampleType]
    SAMPLE_TYPE_FLOAT32: _ClassVar[SampleType]
    SAMPLE_TYPE_FLOAT64: _ClassVar[SampleType]

class Endianness(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ENDIANNESS_UNSPECIFIED: _ClassVar[Endianness]
    ENDIANNESS_LITTLE: _ClassVar[Endianness]
    ENDIANNESS_BIG: _ClassVar[Endianness]

class ResultType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RESULT_TYPE_UNSPECIFIED: _ClassVar[ResultType]
    RESULT_TYPE_VAD: _ClassVar[ResultType]
    RESULT_TYPE_SPEECH: _ClassVar[ResultType]
    RESULT_TYPE_SSL: _ClassVar[ResultType]
    RESULT_TYPE_EMOTION: _ClassVar[ResultType]
    RESULT_TYPE_GENDER: _ClassVar[ResultType]
    RESULT_TYPE_VOICE_ID: _ClassVar[ResultType]
    RESULT_TYPE_GENERIC: _ClassVar[ResultType]

class Completion(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    COMPLETION_UNSPECIFIED: _ClassVar[Completion]
    COMPLETION_COMPLETE: _ClassVar[Completion]
    COMPLETION_TIMED_OUT: _ClassVar[Completion]
    COMPLETION_COMPONENTS_GONE: _ClassVar[Completion]

class MissingReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MISSING_REASON_UNSPECIFIED: _ClassVar[MissingReason]
    MISSING_REASON_TIMED_OUT: _ClassVar[MissingReason]
    MISSING_REASON_GONE: _ClassVar[MissingReason]
SAMPLE_TYPE_UNSPECIFIED: SampleType
SAMPLE_TYPE_INT8: SampleType
SAMPLE_TYPE_UINT8: SampleType
SAMPLE_TYPE_INT16: SampleType
SAMPLE_TYPE_UINT16: SampleType
SAMPLE_TYPE_INT24: SampleType
SAMPLE_TYPE_UINT24: SampleType
SAMPLE_TYPE_INT32: SampleType
SAMPLE_TYPE_UINT32: SampleType
SAMPLE_TYPE_FLOAT32: SampleType
SAMPLE_TYPE_FLOAT64: SampleType
ENDIANNESS_UNSPECIFIED: Endianness
ENDIANNESS_LITTLE: Endianness
ENDIANNESS_BIG: Endianness
RESULT_TYPE_UNSPECIFIED: ResultType
RESULT_TYPE_VAD: ResultType
RESULT_TYPE_SPEECH: ResultType
RESULT_TYPE_SSL: ResultType
RESULT_TYPE_EMOTION: ResultType
RESULT_TYPE_GENDER: ResultType
RESULT_TYPE_VOICE_ID: ResultType
RESULT_TYPE_GENERIC: ResultType
COMPLETION_UNSPECIFIED: Completion
COMPLETION_COMPLETE: Completion
COMPLETION_TIMED_OUT: Completion
COMPLETION_COMPONENTS_GONE: Completion
MISSING_REASON_UNSPECIFIED: MissingReason
MISSING_REASON_TIMED_OUT: MissingReason
MISSING_REASON_GONE: MissingReason

class AudioFormat(_message.Message):
    __slots__ = ("sample_rate_hz", "sample_type", "endianness", "channels")
    SAMPLE_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_TYPE_FIELD_NUMBER: _ClassVar[int]
    ENDIANNESS_FIELD_NUMBER: _ClassVar[int]
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    sample_rate_hz: int
    sample_type: SampleType
    endianness: Endianness
    channels: int
    def __init__(self, sample_rate_hz: _Optional[int] = ..., sample_type: _Optional[_Union[SampleType, str]] = ..., endianness: _Optional[_Union[Endianness, str]] = ..., channels: _Optional[int] = ...) -> None: ...

class Span(_message.Message):
    __slots__ = ("start_ns", "end_ns")
    START_NS_FIELD_NUMBER: _ClassVar[int]
    END_NS_FIELD_NUMBER: _ClassVar[int]
    start_ns: int
    end_ns: int
    def __init__(self, start_ns: _Optional[int] = ..., end_ns: _Optional[int] = ...) -> None: ...

class SslDirection(_message.Message):
    __slots__ = ("source_id", "azimuth_deg", "elevation_deg", "probability", "elevation_known", "track_azimuth_deg", "background")
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    AZIMUTH_DEG_FIELD_NUMBER: _ClassVar[int]
    ELEVATION_DEG_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    ELEVATION_KNOWN_FIELD_NUMBER: _ClassVar[int]
    TRACK_AZIMUTH_DEG_FIELD_NUMBER: _ClassVar[int]
    BACKGROUND_FIELD_NUMBER: _ClassVar[int]
    source_id: str
    azimuth_deg: float
    elevation_deg: float
    probability: float
    elevation_known: bool
    track_azimuth_deg: float
    background: bool
    def __init__(self, source_id: _Optional[str] = ..., azimuth_deg: _Optional[float] = ..., elevation_deg: _Optional[float] = ..., probability: _Optional[float] = ..., elevation_known: _Optional[bool] = ..., track_azimuth_deg: _Optional[float] = ..., background: _Optional[bool] = ...) -> None: ...

class AudioMeta(_message.Message):
    __slots__ = ("segmentation_ended", "segment", "ssl_directions", "end_of_stream", "replay", "broken_off", "speech_until_ns")
    SEGMENTATION_ENDED_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_FIELD_NUMBER: _ClassVar[int]
    SSL_DIRECTIONS_FIELD_NUMBER: _ClassVar[int]
    END_OF_STREAM_FIELD_NUMBER: _ClassVar[int]
    REPLAY_FIELD_NUMBER: _ClassVar[int]
    BROKEN_OFF_FIELD_NUMBER: _ClassVar[int]
    SPEECH_UNTIL_NS_FIELD_NUMBER: _ClassVar[int]
    segmentation_ended: bool
    segment: Span
    ssl_directions: _containers.RepeatedCompositeFieldContainer[SslDirection]
    end_of_stream: bool
    replay: bool
    broken_off: bool
    speech_until_ns: int
    def __init__(self, segmentation_ended: _Optional[bool] = ..., segment: _Optional[_Union[Span, _Mapping]] = ..., ssl_directions: _Optional[_Iterable[_Union[SslDirection, _Mapping]]] = ..., end_of_stream: _Optional[bool] = ..., replay: _Optional[bool] = ..., broken_off: _Optional[bool] = ..., speech_until_ns: _Optional[int] = ...) -> None: ...

class AugmentedAudio(_message.Message):
    __slots__ = ("stream_id", "topic", "publisher", "sequence", "start_ns", "end_ns", "format", "payload", "meta")
    STREAM_ID_FIELD_NUMBER: _ClassVar[int]
    TOPIC_FIELD_NUMBER: _ClassVar[int]
    PUBLISHER_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    START_NS_FIELD_NUMBER: _ClassVar[int]
    END_NS_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    stream_id: str
    topic: str
    publisher: str
    sequence: int
    start_ns: int
    end_ns: int
    format: AudioFormat
    payload: bytes
    meta: AudioMeta
    def __init__(self, stream_id: _Optional[str] = ..., topic: _Optional[str] = ..., publisher: _Optional[str] = ..., sequence: _Optional[int] = ..., start_ns: _Optional[int] = ..., end_ns: _Optional[int] = ..., format: _Optional[_Union[AudioFormat, _Mapping]] = ..., payload: _Optional[bytes] = ..., meta: _Optional[_Union[AudioMeta, _Mapping]] = ...) -> None: ...

class VadResult(_message.Message):
    __slots__ = ("probability",)
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    probability: float
    def __init__(self, probability: _Optional[float] = ...) -> None: ...

class WordTiming(_message.Message):
    __slots__ = ("word", "start_ns", "end_ns", "probability")
    WORD_FIELD_NUMBER: _ClassVar[int]
    START_NS_FIELD_NUMBER: _ClassVar[int]
    END_NS_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    word: str
    start_ns: int
    end_ns: int
    probability: float
    def __init__(self, word: _Optional[str] = ..., start_ns: _Optional[int] = ..., end_ns: _Optional[int] = ..., probability: _Optional[float] = ...) -> None: ...

class Hypothesis(_message.Message):
    __slots__ = ("text", "probability", "words", "raw_text", "match_score", "out_of_set", "logprob", "raw_logprob", "margin")
    TEXT_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    WORDS_FIELD_NUMBER: _ClassVar[int]
    RAW_TEXT_FIELD_NUMBER: _ClassVar[int]
    MATCH_SCORE_FIELD_NUMBER: _ClassVar[int]
    OUT_OF_SET_FIELD_NUMBER: _ClassVar[int]
    LOGPROB_FIELD_NUMBER: _ClassVar[int]
    RAW_LOGPROB_FIELD_NUMBER: _ClassVar[int]
    MARGIN_FIELD_NUMBER: _ClassVar[int]
    text: str
    probability: float
    words: _containers.RepeatedCompositeFieldContainer[WordTiming]
    raw_text: str
    match_score: float
    out_of_set: bool
    logprob: float
    raw_logprob: float
    margin: float
    def __init__(self, text: _Optional[str] = ..., probability: _Optional[float] = ..., words: _Optional[_Iterable[_Union[WordTiming, _Mapping]]] = ..., raw_text: _Optional[str] = ..., match_score: _Optional[float] = ..., out_of_set: _Optional[bool] = ..., logprob: _Optional[float] = ..., raw_logprob: _Optional[float] = ..., margin: _Optional[float] = ...) -> None: ...

class SpeechResult(_message.Message):
    __slots__ = ("hypotheses",)
    HYPOTHESES_FIELD_NUMBER: _ClassVar[int]
    hypotheses: _containers.RepeatedCompositeFieldContainer[Hypothesis]
    def __init__(self, hypotheses: _Optional[_Iterable[_Union[Hypothesis, _Mapping]]] = ...) -> None: ...

class SslResult(_message.Message):
    __slots__ = ("directions", "algorithm", "level_db")
    DIRECTIONS_FIELD_NUMBER: _ClassVar[int]
    ALGORITHM_FIELD_NUMBER: _ClassVar[int]
    LEVEL_DB_FIELD_NUMBER: _ClassVar[int]
    directions: _containers.RepeatedCompositeFieldContainer[SslDirection]
    algorithm: str
    level_db: float
    def __init__(self, directions: _Optional[_Iterable[_Union[SslDirection, _Mapping]]] = ..., algorithm: _Optional[str] = ..., level_db: _Optional[float] = ...) -> None: ...

class LabelResult(_message.Message):
    __slots__ = ("label", "probability", "class_probabilities", "embedding", "quality")
    class ClassProbabilitiesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    LABEL_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    CLASS_PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    EMBEDDING_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    label: str
    probability: float
    class_probabilities: _containers.ScalarMap[str, float]
    embedding: _containers.RepeatedScalarFieldContainer[float]
    quality: UtteranceQuality
    def __init__(self, label: _Optional[str] = ..., probability: _Optional[float] = ..., class_probabilities: _Optional[_Mapping[str, float]] = ..., embedding: _Optional[_Iterable[float]] = ..., quality: _Optional[_Union[UtteranceQuality, _Mapping]] = ...) -> None: ...

class UtteranceQuality(_message.Message):
    __slots__ = ("snr_db", "speech_s", "reason")
    SNR_DB_FIELD_NUMBER: _ClassVar[int]
    SPEECH_S_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    snr_db: float
    speech_s: float
    reason: str
    def __init__(self, snr_db: _Optional[float] = ..., speech_s: _Optional[float] = ..., reason: _Optional[str] = ...) -> None: ...

class NoResult(_message.Message):
    __slots__ = ("reason",)
    REASON_FIELD_NUMBER: _ClassVar[int]
    reason: str
    def __init__(self, reason: _Optional[str] = ...) -> None: ...

class GenericResult(_message.Message):
    __slots__ = ("label", "probability", "class_probabilities", "value", "has_value", "text", "attributes")
    class ClassProbabilitiesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    LABEL_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    CLASS_PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    HAS_VALUE_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    ATTRIBUTES_FIELD_NUMBER: _ClassVar[int]
    label: str
    probability: float
    class_probabilities: _containers.ScalarMap[str, float]
    value: float
    has_value: bool
    text: str
    attributes: _struct_pb2.Struct
    def __init__(self, label: _Optional[str] = ..., probability: _Optional[float] = ..., class_probabilities: _Optional[_Mapping[str, float]] = ..., value: _Optional[float] = ..., has_value: _Optional[bool] = ..., text: _Optional[str] = ..., attributes: _Optional[_Union[_struct_pb2.Struct, _Mapping]] = ...) -> None: ...

class Result(_message.Message):
    __slots__ = ("component", "type", "stream_id", "span", "produced_ns", "sequence", "kind", "instance", "vad", "speech", "ssl", "emotion", "gender", "voice_id", "nothing", "generic")
    COMPONENT_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    STREAM_ID_FIELD_NUMBER: _ClassVar[int]
    SPAN_FIELD_NUMBER: _ClassVar[int]
    PRODUCED_NS_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    INSTANCE_FIELD_NUMBER: _ClassVar[int]
    VAD_FIELD_NUMBER: _ClassVar[int]
    SPEECH_FIELD_NUMBER: _ClassVar[int]
    SSL_FIELD_NUMBER: _ClassVar[int]
    EMOTION_FIELD_NUMBER: _ClassVar[int]
    GENDER_FIELD_NUMBER: _ClassVar[int]
    VOICE_ID_FIELD_NUMBER: _ClassVar[int]
    NOTHING_FIELD_NUMBER: _ClassVar[int]
    GENERIC_FIELD_NUMBER: _ClassVar[int]
    component: str
    type: ResultType
    stream_id: str
    span: Span
    produced_ns: int
    sequence: int
    kind: str
    instance: str
    vad: VadResult
    speech: SpeechResult
    ssl: SslResult
    emotion: LabelResult
    gender: LabelResult
    voice_id: LabelResult
    nothing: NoResult
    generic: GenericResult
    def __init__(self, component: _Optional[str] = ..., type: _Optional[_Union[ResultType, str]] = ..., stream_id: _Optional[str] = ..., span: _Optional[_Union[Span, _Mapping]] = ..., produced_ns: _Optional[int] = ..., sequence: _Optional[int] = ..., kind: _Optional[str] = ..., instance: _Optional[str] = ..., vad: _Optional[_Union[VadResult, _Mapping]] = ..., speech: _Optional[_Union[SpeechResult, _Mapping]] = ..., ssl: _Optional[_Union[SslResult, _Mapping]] = ..., emotion: _Optional[_Union[LabelResult, _Mapping]] = ..., gender: _Optional[_Union[LabelResult, _Mapping]] = ..., voice_id: _Optional[_Union[LabelResult, _Mapping]] = ..., nothing: _Optional[_Union[NoResult, _Mapping]] = ..., generic: _Optional[_Union[GenericResult, _Mapping]] = ...) -> None: ...

class MissingComponent(_message.Message):
    __slots__ = ("component", "type", "reason")
    COMPONENT_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    component: str
    type: ResultType
    reason: MissingReason
    def __init__(self, component: _Optional[str] = ..., type: _Optional[_Union[ResultType, str]] = ..., reason: _Optional[_Union[MissingReason, str]] = ...) -> None: ...

class SslAggregate(_message.Message):
    __slots__ = ("azimuth_deg", "elevation_deg", "concentration", "overlap_s", "directions")
    AZIMUTH_DEG_FIELD_NUMBER: _ClassVar[int]
    ELEVATION_DEG_FIELD_NUMBER: _ClassVar[int]
    CONCENTRATION_FIELD_NUMBER: _ClassVar[int]
    OVERLAP_S_FIELD_NUMBER: _ClassVar[int]
    DIRECTIONS_FIELD_NUMBER: _ClassVar[int]
    azimuth_deg: float
    elevation_deg: float
    concentration: float
    overlap_s: float
    directions: int
    def __init__(self, azimuth_deg: _Optional[float] = ..., elevation_deg: _Optional[float] = ..., concentration: _Optional[float] = ..., overlap_s: _Optional[float] = ..., directions: _Optional[int] = ...) -> None: ...

class LabelAggregate(_message.Message):
    __slots__ = ("label", "probability", "distribution", "overlap_s")
    class DistributionEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    LABEL_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    DISTRIBUTION_FIELD_NUMBER: _ClassVar[int]
    OVERLAP_S_FIELD_NUMBER: _ClassVar[int]
    label: str
    probability: float
    distribution: _containers.ScalarMap[str, float]
    overlap_s: float
    def __init__(self, label: _Optional[str] = ..., probability: _Optional[float] = ..., distribution: _Optional[_Mapping[str, float]] = ..., overlap_s: _Optional[float] = ...) -> None: ...

class Aggregates(_message.Message):
    __slots__ = ("ssl", "emotion", "gender", "voice_id")
    SSL_FIELD_NUMBER: _ClassVar[int]
    EMOTION_FIELD_NUMBER: _ClassVar[int]
    GENDER_FIELD_NUMBER: _ClassVar[int]
    VOICE_ID_FIELD_NUMBER: _ClassVar[int]
    ssl: SslAggregate
    emotion: LabelAggregate
    gender: LabelAggregate
    voice_id: LabelAggregate
    def __init__(self, ssl: _Optional[_Union[SslAggregate, _Mapping]] = ..., emotion: _Optional[_Union[LabelAggregate, _Mapping]] = ..., gender: _Optional[_Union[LabelAggregate, _Mapping]] = ..., voice_id: _Optional[_Union[LabelAggregate, _Mapping]] = ...) -> None: ...

class FusedResult(_message.Message):
    __slots__ = ("id", "revision", "fusion", "stream_id", "anchor", "results", "completion", "missing_components", "published_ns", "missing", "aggregates", "seq")
    ID_FIELD_NUMBER: _ClassVar[int]
    REVISION_FIELD_NUMBER: _ClassVar[int]
    FUSION_FIELD_NUMBER: _ClassVar[int]
    STREAM_ID_FIELD_NUMBER: _ClassVar[int]
    ANCHOR_FIELD_NUMBER: _ClassVar[int]
    RESULTS_FIELD_NUMBER: _ClassVar[int]
    COMPLETION_FIELD_NUMBER: _ClassVar[int]
    MISSING_COMPONENTS_FIELD_NUMBER: _ClassVar[int]
    PUBLISHED_NS_FIELD_NUMBER: _ClassVar[int]
    MISSING_FIELD_NUMBER: _ClassVar[int]
    AGGREGATES_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    id: int
    revision: int
    fusion: str
    stream_id: str
    anchor: Result
    results: _containers.RepeatedCompositeFieldContainer[Result]
    completion: Completion
    missing_components: _containers.RepeatedScalarFieldContainer[str]
    published_ns: int
    missing: _containers.RepeatedCompositeFieldContainer[MissingComponent]
    aggregates: Aggregates
    seq: int
    def __init__(self, id: _Optional[int] = ..., revision: _Optional[int] = ..., fusion: _Optional[str] = ..., stream_id: _Optional[str] = ..., anchor: _Optional[_Union[Result, _Mapping]] = ..., results: _Optional[_Iterable[_Union[Result, _Mapping]]] = ..., completion: _Optional[_Union[Completion, str]] = ..., missing_components: _Optional[_Iterable[str]] = ..., published_ns: _Optional[int] = ..., missing: _Optional[_Iterable[_Union[MissingComponent, _Mapping]]] = ..., aggregates: _Optional[_Union[Aggregates, _Mapping]] = ..., seq: _Optional[int] = ...) -> None: ...

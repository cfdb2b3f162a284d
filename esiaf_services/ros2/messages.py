"""The ROS 2 message types the ros2 service publishes, declared for Cyclone DDS as a ROS 2 node sees them.

Layouts are those of ``hri_msgs`` 2.0.0 (ros4hri/hri_msgs, tag 2.0.0, ROS 2 Humble), ``std_msgs``,
``builtin_interfaces`` and ``geometry_msgs``: fields in the ``.msg`` order, ``string`` unbounded,
``float64``/``float32``/``int8``/``uint8`` as declared. ROS 2 names the DDS type of ``pkg/Msg``
``pkg::msg::dds_::Msg_`` and the DDS topic of ``/a/b`` ``rt/a/b`` (rmw_cyclonedds_cpp and
rmw_fastrtps_cpp alike); the data is plain CDR (XCDR1), which ROS 2's RMWs send and accept.

``audio_common_msgs/AudioData`` is ros-drivers/audio_common's (its ROS 2 branch): ``uint8[] data``.

``LiveSpeech.language`` (2.0.0) is the IETF language code; newer hri_msgs call that field ``locale``.
CDR carries no field names, so both read the same bytes.
"""
# no `from __future__ import annotations`: cyclonedds resolves the field types at run time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float32, float64, int8, int32, sequence, uint8, uint32

if TYPE_CHECKING:  # a list to the type checker; a DDS sequence to cyclonedds, which reads the annotation
    Strings = list[str]
    Bytes = bytes
else:
    Strings = sequence[str]
    Bytes = sequence[uint8]

# hri_msgs/IdsMatch constants
VOICE, PERSON = 4, 1
# hri_msgs/SoftBiometrics gender constants
UNDEFINED, FEMALE, MALE = 0, 1, 2


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32

    @classmethod
    def from_ns(cls, ns: int) -> "Time":
        return cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Bool(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):
    data: bool


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Vector3Stamped(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3Stamped_"):
    header: Header
    vector: Vector3


@dataclass
class IdsList(IdlStruct, typename="hri_msgs::msg::dds_::IdsList_"):
    header: Header
    ids: Strings  # string[]


@dataclass
class LiveSpeech(IdlStruct, typename="hri_msgs::msg::dds_::LiveSpeech_"):
    header: Header
    incremental: str
    final: str
    confidence: float64
    language: str


@dataclass
class IdsMatch(IdlStruct, typename="hri_msgs::msg::dds_::IdsMatch_"):
    id1: str
    id1_type: int8
    id2: str
    id2_type: int8
    confidence: float32


@dataclass
class Expression(IdlStruct, typename="hri_msgs::msg::dds_::Expression_"):
    header: Header
    expression: str
    valence: float32
    arousal: float32
    confidence: float32


@dataclass
class SoftBiometrics(IdlStruct, typename="hri_msgs::msg::dds_::SoftBiometrics_"):
    header: Header
    age: uint8
    age_confidence: float32
    gender: uint8
    gender_confidence: float32


@dataclass
class AudioData(IdlStruct, typename="audio_common_msgs::msg::dds_::AudioData_"):
    """audio_common_msgs/AudioData (ros-drivers/audio_common, ROS 2): ``uint8[] data``, the raw bytes;
    here mono signed 16 bit little endian samples at the bridge's ``audio_sample_rate_hz``."""
    # uint8[]: declared as a sequence of uint8 (a bytes field would be octets to a peer that matches types);
    # cyclonedds takes bytes for it, and writes it a byte at a time (about 14 ms for 3 s of audio)
    data: Bytes

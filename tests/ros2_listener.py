"""A ROS 2 subscriber without ROS, for tests/test_ros2.py: Cyclone DDS readers on ROS 2's names for
REP-155's voice topics, the types declared here from the hri_msgs 2.0.0, std_msgs and audio_common_msgs
.msg files (not taken from the bridge). Prints one JSON line per sample: {"topic", "type", "received_s",
"data"}; an AudioData's bytes in base64.

    python tests/ros2_listener.py --seconds 60 [--namespace /robot1 ...] VOICE_ID ...
"""
import argparse
import base64
import json
import os
import sys
import time
from dataclasses import asdict, dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float32, float64, int8, int32, sequence, uint8, uint32
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):  # int32 sec, uint32 nanosec
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):  # Time stamp, string frame_id
    stamp: Time
    frame_id: str


@dataclass
class Bool(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):  # bool data
    data: bool


@dataclass
class IdsList(IdlStruct, typename="hri_msgs::msg::dds_::IdsList_"):  # Header header, string[] ids
    header: Header
    ids: sequence[str]


@dataclass
class LiveSpeech(IdlStruct, typename="hri_msgs::msg::dds_::LiveSpeech_"):
    header: Header  # std_msgs/Header header
    incremental: str  # string incremental
    final: str  # string final
    confidence: float64  # float64 confidence
    language: str  # string language (hri_msgs 2.0.0)


@dataclass
class IdsMatch(IdlStruct, typename="hri_msgs::msg::dds_::IdsMatch_"):
    id1: str
    id1_type: int8
    id2: str
    id2_type: int8
    confidence: float32


@dataclass
class AudioData(IdlStruct, typename="audio_common_msgs::msg::dds_::AudioData_"):  # ros-drivers/audio_common, ROS 2
    data: sequence[uint8]  # uint8[] data


def as_json(sample) -> dict:
    data = asdict(sample)
    if isinstance(sample, AudioData):
        data["data"] = base64.b64encode(bytes(sample.data)).decode()
    return data


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--namespace", action="append", default=[], help="repeatable; default: none")
    parser.add_argument("ids", nargs="*")
    args = parser.parse_args()
    participant = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID") or 0))  # as a ROS 2 node reads it
    qos = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.Volatile,
              Policy.History.KeepLast(10))
    wanted = []
    for ns in args.namespace or [""]:
        wanted += [(f"{ns}/humans/voices/tracked", IdsList), (f"{ns}/humans/candidate_matches", IdsMatch)]
        for voice in args.ids:
            wanted += [(f"{ns}/humans/voices/{voice}/speech", LiveSpeech),
                       (f"{ns}/humans/voices/{voice}/is_speaking", Bool),
                       (f"{ns}/humans/voices/{voice}/audio", AudioData)]
    readers = [(name, kind, DataReader(participant, Topic(participant, "rt" + name, kind, qos=qos), qos=qos))
               for name, kind in wanted]
    print(json.dumps({"ready": True}), flush=True)
    deadline = time.monotonic() + args.seconds
    while time.monotonic() < deadline:
        for name, kind, reader in readers:
            for sample in reader.take(N=100):
                if not isinstance(sample, kind):  # an instance's end (its writer gone), not data
                    continue
                print(json.dumps({"topic": name, "type": kind.__name__, "received_s": time.time(),
                                  "data": as_json(sample)}), flush=True)
        time.sleep(0.01)
    return 0


if __name__ == "__main__":
    sys.exit(main())

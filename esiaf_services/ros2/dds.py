"""The ros2 service's DDS side: one Cyclone DDS participant, a writer per ROS topic with ROS 2's
default QoS (reliable, volatile, keep last 10), made on first use."""
from __future__ import annotations

from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from cyclonedds.util import duration

# rmw's defaults (rmw_qos_profile_default); plain CDR (XCDR1) as ROS 2's RMWs send and expect it
ROS2_DEFAULT_QOS = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.Volatile,
                       Policy.History.KeepLast(10),
                       Policy.DataRepresentation(use_cdrv0_representation=True))
MAX_WRITERS = 1024  # topics written at most; past it the oldest writer is closed (voices come and go)


def dds_topic(ros_topic: str) -> str:
    """ROS 2's DDS topic of a ROS topic: ``/humans/voices/tracked`` -> ``rt/humans/voices/tracked``."""
    return "rt" + ros_topic


class Writers:
    """A DataWriter per (ROS topic, type) on one participant of ``domain``."""

    def __init__(self, domain: int) -> None:
        self.participant = DomainParticipant(domain)
        self.writers: dict[tuple[str, type], DataWriter] = {}

    def write(self, ros_topic: str, sample: Any) -> None:
        key = (ros_topic, type(sample))
        writer = self.writers.get(key)
        if writer is None:
            if len(self.writers) >= MAX_WRITERS:
                self.writers.pop(next(iter(self.writers)))
            topic = Topic(self.participant, dds_topic(ros_topic), type(sample), qos=ROS2_DEFAULT_QOS)
            writer = self.writers[key] = DataWriter(self.participant, topic, qos=ROS2_DEFAULT_QOS)
        writer.write(sample)

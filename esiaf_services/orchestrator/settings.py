"""The orchestrator's settings (defaults < YAML file < ESIAF_ORCHESTRATOR_* < command line)."""
from __future__ import annotations

import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator

from esiaf.control_messages import BargeInPolicy
from esiaf.results import KIND_PATTERN, RESULT_TYPES
from esiaf.settings import StrictModel, load_settings

from .registry.negotiation import Strategy

SERVICE = "orchestrator"

# Result kinds a component can produce (its kind; "other" produces none): the built-in
# ones of the proto, and any other name (an analyser in its own folder), e.g. "rate".
ResultTypeName = Annotated[str, Field(pattern=KIND_PATTERN, examples=list(RESULT_TYPES),
                                      description="a result kind: built in (" + ", ".join(RESULT_TYPES)
                                                  + ") or any other name like 'rate'")]
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


class FusionSettings(StrictModel):
    """One configured fusion: results of ``fuse`` types gathered around each ``anchor`` result."""

    name: str = Field(min_length=1, description="name of the fusion, as in fused results")
    anchor: ResultTypeName = Field(description="result type whose results anchor a fused result")
    fuse: list[ResultTypeName] = Field(default_factory=list,
                                       description="result types fused with each anchor result")
    stream: str | None = Field(default=None, description="only anchor results of this stream")

    @model_validator(mode="after")
    def _consistent(self) -> FusionSettings:
        if self.anchor in self.fuse:
            raise ValueError(f"fusion {self.name!r}: the anchor type {self.anchor} cannot also be "
                             "fused with itself (each anchor has its own window)")
        repeated = sorted({t for t in self.fuse if self.fuse.count(t) > 1})
        if repeated:
            raise ValueError(f"fusion {self.name!r}: fuse names a type more than once: "
                             f"{', '.join(repeated)}")
        return self


class TimeoutSettings(StrictModel):
    """How long a fusion waits for a component: factor x its running mean latency, or its mean plus
    deviations x its running mean deviation if that is longer, clamped."""

    factor: float = Field(default=1.5, gt=0, description="x the component's mean latency")
    deviations: float = Field(default=4.0, ge=0, description="or its mean latency plus this many mean "
                                                             "deviations, if longer (0: the factor alone)")
    factors: dict[str, float] = Field(default_factory=dict,
                                      description="per component name: its own factor")
    initial_s: float = Field(default=2.0, gt=0, description="before a latency is known")
    min_s: float = Field(default=0.05, ge=0)
    max_s: float = Field(default=10.0, gt=0)
    memory_s: float = Field(default=120.0, gt=0,
                            description="capture time kept in memory per stream, for late "
                                        "results and anchors that come after their results")
    revision_interval_s: float = Field(default=0.5, ge=0,
                                       description="at most one revision per fused result this often: "
                                                   "late results that come sooner are coalesced")

    @model_validator(mode="after")
    def _bounds(self) -> TimeoutSettings:
        if self.min_s > self.max_s:
            raise ValueError(f"min_s ({self.min_s}) must not exceed max_s ({self.max_s})")
        bad = sorted(name for name, factor in self.factors.items() if factor <= 0)
        if bad:
            raise ValueError(f"factors must be positive; not for {', '.join(bad)}")
        return self


class OrchestratorSettings(StrictModel):
    host: str = "127.0.0.1"  # where the HTTP, control and results sockets bind
    port: int = Field(default=8000, ge=0, le=65535)  # HTTP (REST and websocket)
    advertise_host: str = ""  # how components reach us; defaults to host (hostname if 0.0.0.0)
    control_port: int = Field(default=5560, ge=0, le=65535)  # 0 = any free port
    results_port: int = Field(default=5561, ge=0, le=65535)  # 0 = any free port
    db_path: str = "esiaf.db"
    # a working component beats this often (every beat wakes it and the orchestrator: 0.5 s cost the
    # framework about 20 CPU-s per hour of audio more, docs/benchmarks.md); a process that dies is found through its
    # closed connection (disconnect_grace_s), so the beats only find one that hangs or is cut off
    heartbeat_interval_s: float = Field(default=2.0, gt=0)
    dead_after_s: float = Field(default=8.0, gt=0)
    # a component that has had nothing to do (no audio, no results, no state change) for this long beats
    # this often instead, and is dead once silent for dead_after_s plus the difference; it goes back to
    # heartbeat_interval_s at once when it has work. Equal to heartbeat_interval_s: it never slows down
    idle_heartbeat_interval_s: float = Field(default=5.0, gt=0)
    # a component whose control connection closed (its process died: the kernel closes its sockets) and
    # that has not said anything on a new one this long after is dead, without waiting for dead_after_s
    disconnect_grace_s: float = Field(default=1.0, ge=0)
    # a component with inputs that was seen to die without ending a stream (its connection closed, or its
    # launcher said so) holds that stream's end this long, for a restarted instance of it to come back and
    # finish its backlog; after it, the stream ends without it. 0: the stream ends without it at once
    stream_end_grace_s: float = Field(default=10.0, ge=0)
    # ... one declared dead for its silence alone (a stall: frozen, or a native call holding it; 2.5 s on a
    # loaded machine were enough) holds it this long, for it to come back with its backlog: the time a
    # consumer that stops reading keeps its audio (esiaf/transport.py STALL_MS)
    stream_end_stall_grace_s: float = Field(default=60.0, ge=0)
    format_strategy: Strategy = "min_conversions"  # how each topic's wire format is chosen
    # what a stream's player does when a person starts speaking while the robot plays (a barge-in):
    # stop, duck (the rest of the item lower) or ignore; per stream: PUT /streams/{stream}/barge-in
    barge_in_policy: BargeInPolicy = "stop"
    # fusion's rule for the robot's own voice takes a grammar recogniser's out-of-set hypothesis (no sentence of
    # its set; the words it forced onto the sound) for nothing recognised, not for a person's other words: on
    # with the vad's gain (vad.silero.level_max_gain_db), where the room's babble under the robot is decoded so
    # (300 s of talk: 11 and 12 fused as a user's -> 2 and 0; docs/benchmarks.md "Out-of-set words are no
    # person"); off by default: a question over the robot decoded out of the set then needs the canceller's
    # evidence to stay a person's (seed 2 with the gain: directions 12 -> 10 of 18)
    robot_out_of_set_is_nothing: bool = False
    # each recognised utterance with its direction, emotion, gender and voice; a fusion waits only
    # for live components of a fused type, so without ssl/emotion/gender/voiceid nothing waits
    fusions: list[FusionSettings] = Field(
        default_factory=lambda: [FusionSettings(name="speech", anchor="speech",
                                                fuse=["ssl", "emotion", "gender", "voice_id"])])
    timeouts: TimeoutSettings = Field(default_factory=TimeoutSettings)
    # a WAV enrolment (POST /voices/{name}) also enrols this many reverberant noisy copies of the WAV
    # (esiaf/speech/speaker/augment.py ROOMS, source "wav-room"), so a voice enrolled clean is known across a
    # room (bench/voiceid.py --room-enrolment, d-vector closed set in a room: 35.4 % clean only, 43.8 % with 2,
    # 42.0 % with 4), but at the thresholds, calibrated on clean enrolments, clean neutral speech is named right
    # 91.8 % of the time with 2 against 100 %: 0 (the default), the clean embedding alone, until they are
    # calibrated with copies; needs pyroomacoustics (the ssl extra)
    enrolment_room_copies: int = Field(default=0, ge=0, le=4)
    log_level: str = "INFO"
    max_body_bytes: int = Field(default=1024 * 1024, gt=0)  # HTTP request bodies larger than this get 413
    # an HTTP request (headers and body) must have come whole this long after its first byte, or its
    # connection is closed (connections.py): a peer cannot hold connections with requests it never ends
    request_timeout_s: float = Field(default=10.0, gt=0)
    max_connections_per_peer: int = Field(default=256, gt=0)  # HTTP connections of one IP address at once
    token: str = ""  # required on every request but /health once set; default ESIAF_TOKEN / ESIAF_TOKEN_FILE
    allowed_origins: list[str] = Field(default_factory=list)  # browser origins whose websockets are accepted
    # HTTPS and wss: the certificate (chain) and its private key, PEM files; clients check it against
    # the system's CAs or the file ESIAF_TLS_CA names. Both or neither.
    tls_cert: str = ""
    tls_key: str = ""

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, value: str) -> str:
        level = value.upper()
        if level not in LOG_LEVELS:
            raise ValueError(f"must be one of {', '.join(LOG_LEVELS)}, not {value!r}")
        return level

    @model_validator(mode="after")
    def _consistent(self) -> OrchestratorSettings:
        names = [f.name for f in self.fusions]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"fusion names must be unique; repeated: {', '.join(duplicates)}")
        if bool(self.tls_cert) != bool(self.tls_key):
            raise ValueError("tls_cert and tls_key go together: give both (HTTPS) or neither")
        if self.dead_after_s <= self.heartbeat_interval_s:
            raise ValueError(f"dead_after_s ({self.dead_after_s}) must be longer than "
                             f"heartbeat_interval_s ({self.heartbeat_interval_s})")
        if self.idle_heartbeat_interval_s < self.heartbeat_interval_s:
            raise ValueError(f"idle_heartbeat_interval_s ({self.idle_heartbeat_interval_s}) must not be shorter "
                             f"than heartbeat_interval_s ({self.heartbeat_interval_s})")
        return self

    def advertised_host(self) -> str:
        """The host name components use to reach the orchestrator's ZeroMQ sockets."""
        if self.advertise_host:
            return self.advertise_host
        if self.host in ("0.0.0.0", "::", "*", ""):
            return socket.gethostname()
        return self.host


def load(config: str | Path | None = None, env: Mapping[str, str] | None = None,
         **overrides: Any) -> OrchestratorSettings:
    """Builds the settings; raises :class:`esiaf.settings.SettingsError` with one clear line."""
    return load_settings(OrchestratorSettings, SERVICE, config=config, env=env, **overrides)

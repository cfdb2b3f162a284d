"""Who is registered, which format each topic carries, and what each component must know.

Pure bookkeeping, no sockets: every registration, removal and death recomputes the
topics' formats (negotiation.py); the control plane asks :meth:`Registry.changed_states`
after every change and pushes what it returns.
"""
from __future__ import annotations

import logging
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from esiaf.binding import derive_key
from esiaf.control_messages import ClockReport, State

from .assignment import Assignments
from .negotiation import Declaration, Format, Strategy, choose

log = logging.getLogger(__name__)

KEEP_DEPARTED = 1000  # dead / replaced components kept for GET /components?include_dead=true


class TopicConflict(Exception):
    """A declared format whose channel count differs from its topic's (HTTP 409)."""


class InstanceConflict(Exception):
    """An instance id that a live instance, another process, holds (HTTP 409)."""

    def __init__(self, message: str, live: Component):
        super().__init__(message)
        self.live = live


@dataclass
class Component:
    component_id: str
    name: str
    kind: str  # the result kind it produces (other: none)
    stream_id: str
    inputs: dict[str, Format]
    outputs: dict[str, Format]
    audio_endpoint: str | None
    host: str
    pid: int | None
    info: dict[str, Any]
    audio_public_key: str | None = None  # Z85 CURVE key of its audio output (with CURVE keys)
    incarnation: str | None = None  # the registering process's secret token: its own re-registrations
    # this registration's control secret: every control message must carry it (a new one for every
    # registration); the routing id that last presented it (state is pushed there only); with CURVE,
    # the public key its first such message came with (every later one must come with it too)
    control_key: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    key_id: str = ""  # names this registration: its results carry it with their MAC (esiaf/binding.py)
    control_route: bytes | None = None
    control_fd: int | None = None  # the file descriptor of that connection (the monitor names a closed one by it)
    control_peer_key: str | None = None
    registered_ns: int = field(default_factory=time.time_ns)
    last_seen_ns: int = field(default_factory=time.time_ns)
    last_seen_mono: float = field(default_factory=time.monotonic)
    heartbeats: int = 0
    # the interval its last heartbeat said it beats at (None: none said, the fast one), and how much
    # longer than the fast one that is: it is dead once silent for dead_after_s plus this
    beat_interval_s: float | None = None
    extra_silence_s: float = 0.0
    results_received: int = 0
    stats: dict[str, Any] | None = None
    status: str = "alive"  # alive, dead (silent too long), replaced (its process registered again)
    departed_ns: int | None = None
    # dead for its silence alone, its connection open (a stall: frozen, or a native call holding it), not
    # seen to die: it may come back with its backlog, so a stream's end waits longer for it
    went_silent: bool = False
    served_at_departure: list[str] = field(default_factory=list)  # the streams it served when it died or left
    pushed_state: State | None = None  # the state this component last got from us (without its version)
    state_version: int = 0  # pushed_state's number: a new one for every change (heartbeats say which they have)
    offered_at: tuple[int, int] | None = None  # the registry's version when pushed_state was last computed
    # our clock minus its host's, and how sure (half the best round trip), as its heartbeats report
    # them (esiaf/clock.py); None until it has measured
    clock_offset_ns: int | None = None
    clock_uncertainty_ns: int | None = None

    def note_clock(self, clock: ClockReport | None) -> None:
        """The clock estimate of a heartbeat, if it has one (bounded by ClockReport)."""
        if clock is not None:
            self.clock_offset_ns, self.clock_uncertainty_ns = clock.offset_ns, clock.uncertainty_ns

    def offer(self, state: State) -> bool:
        """Makes ``state`` the one it is to have; True (and a new ``state_version``) if it changed."""
        if state == self.pushed_state:
            return False
        self.pushed_state = state
        self.state_version += 1
        return True

    def beats_every(self, said: float | None, fast_s: float, slowest_s: float) -> bool:
        """The interval a heartbeat says it beats at (a peer's: clamped to the settings' range); True if
        it is shorter than before (so may be its death, if it falls silent now)."""
        if said is None:
            return False
        before = self.extra_silence_s
        self.beat_interval_s = min(max(float(said), fast_s), slowest_s)
        self.extra_silence_s = self.beat_interval_s - fast_s
        return self.extra_silence_s < before

    def silent_too_long_at(self, dead_after_s: float) -> float:
        """When it is dead if it says nothing more (monotonic)."""
        return self.last_seen_mono + dead_after_s + self.extra_silence_s

    def touch(self) -> None:
        self.last_seen_mono = time.monotonic()
        self.last_seen_ns = time.time_ns()

    def holds_stream_end_until_ns(self, grace_ns: float, stall_grace_ns: float) -> float | None:
        """Until when, dead without ending a stream, it may yet come back to end it (a component with
        inputs only): its death plus the grace for a stall if it went silent, else for a restart."""
        if self.status != "dead" or not self.inputs:
            return None
        return (self.departed_ns or 0) + (stall_grace_ns if self.went_silent else grace_ns)


def describe(fmt: Format) -> str:
    return (f"{fmt['sample_rate_hz']} Hz {fmt['sample_type']} {fmt['endianness']}-endian "
            f"{fmt['channels']} ch")


class Registry:
    def __init__(self, strategy: Strategy = "min_conversions") -> None:
        self.strategy = strategy
        self.live: dict[str, Component] = {}  # by component_id, in registration order
        self.departed: OrderedDict[str, Component] = OrderedDict()
        self.assigned: dict[str, Format] = {}  # each topic's internal format
        self.assignments = Assignments()  # which instance of a replicated service serves each stream
        self.generation = 0  # a new number at every recompute(): with the assignments' version, states may differ
        # what control keys are derived from (esiaf/binding.py): the orchestrator sets the one its
        # database keeps, so that it can check results of registrations made before a restart
        self.secret = secrets.token_bytes(32)

    # changes
    def register(self, *, name: str, kind: str, stream_id: str,
                 inputs: dict[str, Format], outputs: dict[str, Format],
                 audio_endpoint: str | None, host: str, pid: int | None,
                 info: dict[str, Any], audio_public_key: str | None = None,
                 instance: str | None = None, incarnation: str | None = None) -> tuple[Component, Component | None]:
        """Adds an instance of service ``name`` under the id ``instance`` (or a new one); returns it
        and its own earlier registration that it replaces (the same process registering again: the
        same ``incarnation``). Raises InstanceConflict for another process's live instance id."""
        previous = self.live.get(instance) if instance else None
        if previous is not None and (incarnation is None or previous.incarnation != incarnation):
            raise InstanceConflict(f"instance id {instance!r} is held by a live instance (host "
                                   f"{previous.host or '?'}, pid {previous.pid}); give this one another "
                                   "instance id, or let the other stop or be declared dead first", previous)
        self._check_channels(name, inputs, outputs, exclude=previous)
        if previous is not None:  # the same process, registering again: the new record is the instance
            del self.live[previous.component_id]
            previous.status = "replaced"
        component_id = instance or self._new_id(name)
        self.departed.pop(component_id, None)
        key_id = secrets.token_urlsafe(12)
        component = Component(component_id=component_id, name=name, kind=kind,
                              stream_id=stream_id, inputs=inputs, outputs=outputs,
                              audio_endpoint=audio_endpoint, host=host, pid=pid, info=info,
                              audio_public_key=audio_public_key, incarnation=incarnation, key_id=key_id,
                              control_key=derive_key(self.secret, component_id, key_id))
        self.live[component_id] = component
        self.recompute()
        self.offer_current(component)
        return component, previous

    def remove(self, component_id: str) -> Component | None:
        """Drops a component that shut down cleanly (it is not kept as departed)."""
        component = self.live.pop(component_id, None)
        if component is not None:
            self.recompute()
        return component

    def declare_dead(self, component_id: str) -> Component | None:
        """Declares a live component dead now: its process is known to have died (its launcher saw it)."""
        component = self.live.get(component_id)
        if component is not None:
            self._depart(component, "dead")
            self.recompute()
        return component

    def expire(self, dead_after_s: float, now_mono: float | None = None) -> list[Component]:
        """Drops and returns the components silent for more than ``dead_after_s`` (plus, for one that
        said it beats slowly while idle, the difference to the fast interval)."""
        now_mono = time.monotonic() if now_mono is None else now_mono
        dead = [c for c in self.live.values() if now_mono > c.silent_too_long_at(dead_after_s)]
        for component in dead:
            component.went_silent = True
            self._depart(component, "dead")
        if dead:
            self.recompute()
        return dead

    def recompute(self) -> dict[str, Format]:
        """Chooses every topic's format again; returns the topics whose format changed. Called after
        every change of who is live (any state may differ now)."""
        self.generation += 1
        assigned, changed = {}, {}
        for topic in self.topic_names():
            current = self.assigned.get(topic)
            assigned[topic] = choose(self.declarations(topic), self.strategy, current)
            if assigned[topic] != current:
                changed[topic] = assigned[topic]
                log.info("event=format_assigned topic=%s format=%s previous=%s strategy=%s", topic,
                         describe(assigned[topic]), describe(current) if current else "-", self.strategy)
        self.assigned = assigned
        self.assignments.update(self.with_inputs())
        return changed

    def _depart(self, component: Component, status: str) -> None:
        component.served_at_departure = sorted(
            s for s, i in self.assignments.serving(component.name).items() if i == component.component_id)
        self.live.pop(component.component_id, None)
        component.status = status
        component.departed_ns = time.time_ns()
        self.departed[component.component_id] = component
        while len(self.departed) > KEEP_DEPARTED:
            self.departed.popitem(last=False)

    def _new_id(self, name: str) -> str:
        while True:
            component_id = f"{name}-{secrets.token_hex(3)}"
            if component_id not in self.live and component_id not in self.departed:
                return component_id

    def _check_channels(self, name: str, inputs: dict[str, Format], outputs: dict[str, Format],
                        exclude: Component | None) -> None:
        declared = self._declared(exclude)
        for topic, fmt in [*outputs.items(), *inputs.items()]:
            if topic not in declared:
                declared[topic] = (fmt, name)
                continue
            other, other_name = declared[topic]
            if other["channels"] != fmt["channels"]:
                raise TopicConflict(
                    f"topic {topic!r}: {name!r} declares {describe(fmt)}, but {other_name!r} "
                    f"already declared {describe(other)} on it; channel counts are never "
                    "converted (put a channel splitter in between)")

    def _declared(self, exclude: Component | None) -> dict[str, tuple[Format, str]]:
        """A format already declared on each topic by a live component, with its name."""
        declared: dict[str, tuple[Format, str]] = {}
        for component in self.live.values():
            if component is exclude:
                continue
            for topic, fmt in [*component.outputs.items(), *component.inputs.items()]:
                declared.setdefault(topic, (fmt, component.name))
        return declared

    # queries
    def get(self, component_id: str) -> Component | None:
        return self.live.get(component_id)

    def by_name(self, name: str) -> Component | None:
        """The first live instance of service ``name``."""
        return next((c for c in self.live.values() if c.name == name), None)

    def instances(self, name: str) -> list[Component]:
        """The live instances of service ``name``, in registration order."""
        return [c for c in self.live.values() if c.name == name]

    def add_stream(self, stream_id: str, served_by: Component | None = None) -> bool:
        """A stream is active (announced, or a result of it came): each replicated service gives it
        to one instance. True if that is news (states may have to be pushed)."""
        if not self.assignments.add_stream(stream_id, served_by):
            return False
        self.assignments.update(self.with_inputs())
        return True

    def end_stream(self, stream_id: str) -> None:
        self.assignments.end_stream(stream_id)

    def formats(self) -> dict[str, Format]:
        """The format assigned to each topic (as of the last registration, removal or death)."""
        return dict(self.assigned)

    def declarations(self, topic: str) -> list[Declaration]:
        """Every live component's format on ``topic``, in registration order."""
        declared = []
        for component in self.live.values():
            if topic in component.outputs:
                declared.append(Declaration(component.name, "producer", component.outputs[topic]))
            if topic in component.inputs:
                declared.append(Declaration(component.name, "consumer", component.inputs[topic]))
        return declared

    def producers(self, topic: str) -> list[Component]:
        return [c for c in self.live.values() if topic in c.outputs]

    def consumers(self, topic: str) -> list[Component]:
        return [c for c in self.live.values() if topic in c.inputs]

    def state_of(self, component: Component, formats: dict[str, Format] | None = None) -> State:
        """The full state a component is told: its peers (with their CURVE keys, where they gave
        one), the formats of its topics and, with outputs, its consumers."""
        formats = self.formats() if formats is None else formats
        producers = {topic: [p for p in self.producers(topic) if p is not component and p.audio_endpoint]
                     for topic in component.inputs}
        peers = {topic: [p.audio_endpoint for p in found] for topic, found in producers.items()}
        topics = [*component.inputs, *(t for t in component.outputs if t not in component.inputs)]
        peer_keys = {p.audio_endpoint: p.audio_public_key for found in producers.values() for p in found
                     if p.audio_public_key}
        # one of several instances: only the streams it serves (None: all)
        streams = self.assignments.streams_of(component, len(self.instances(component.name))) \
            if component.inputs else None
        # with outputs: the only subscribers its audio output takes (esiaf/gate.py)
        consumers = sorted({c.component_id for topic in component.outputs for c in self.consumers(topic)
                            if c is not component}) if component.outputs else None
        return State(peers=peers, formats={t: formats[t] for t in topics},
                     peer_keys=peer_keys or None, streams=streams, consumers=consumers)

    def changed_states(self) -> list[tuple[Component, State]]:
        """Live components whose state differs from what they last got, with the new state."""
        formats = self.formats()
        changed = []
        for component in self.live.values():
            state = self.state_of(component, formats)
            component.offered_at = self.version()
            if component.offer(state):
                changed.append((component, state))
        return changed

    def version(self) -> tuple[int, int]:
        """Changes whenever a state may have: every live set and format change (recompute()), every
        stream assignment change."""
        return self.generation, self.assignments.version

    def offer_current(self, component: Component) -> None:
        """Makes the state the registry now gives ``component`` the one it is to have (a new
        ``state_version`` if that differs): what every heartbeat does, so a change no push has
        carried yet is answered in full. Computed again only after a change, not at
        every heartbeat: most beats find it current."""
        if component.offered_at != (version := self.version()):
            component.offer(self.state_of(component))
            component.offered_at = version

    def all(self, include_departed: bool = False) -> list[Component]:
        components = list(self.live.values())
        if include_departed:
            components += list(self.departed.values())
        return components

    def topic_names(self) -> list[str]:
        names: dict[str, None] = {}
        for component in self.live.values():
            names.update(dict.fromkeys(component.outputs))
            names.update(dict.fromkeys(component.inputs))
        return sorted(names)

    def with_inputs(self) -> list[Component]:
        return [c for c in self.live.values() if c.inputs]

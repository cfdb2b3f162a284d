"""The processor: what a user writes to make an ESIAF component.

A processor declares what it takes and gives (its input and output topics with the format it
wants on each, its service name and the kind of result it produces), loads what it needs in
:meth:`Processor.setup` (which may fail cleanly with :class:`SetupError`), and handles one message
at a time in its ``on_...`` methods. It publishes audio and emits results through
``self.context`` (a :class:`ProcessorContext`, esiaf.node's Context in a pipeline), which the runtime
that runs it gives it.

It owns no socket, thread or registration: a node (esiaf/node.py) runs one processor, or several
in one process, over ZeroMQ; esiaf.testing runs one in-process on a WAV file. Most services
subclass :class:`esiaf.Component`, a processor with the context's actions as its own methods.
"""
from __future__ import annotations

import logging
import uuid
from collections.abc import Iterable
from typing import Any, ClassVar, Protocol

import numpy as np

from esiaf.audio import Audio
from esiaf.control_messages import Command
from esiaf.formats import AudioFormat
from esiaf.proto import esiaf_pb2 as pb
from esiaf.results import valid_kind
from esiaf.settings import ComponentSettings


class ProcessorContext(Protocol):
    """What a processor may do through its runtime: publish, emit, and ask about its run.

    The processor knows this interface, never the runtime behind it (esiaf/node.py's Context in a
    pipeline, esiaf/testing.py's in a test), so the SDK's runtime can change without its users.
    """

    @property
    def stopping(self) -> bool: ...

    def stop(self, exit_code: int = 0) -> None: ...

    def publish(self, topic: str, audio: bytes | np.ndarray, start_ns: int, end_ns: int, *,
                stream_id: str | None = None, segmentation_ended: bool = False,
                segment: tuple[int, int] | None = None, ssl_directions: Iterable[pb.SslDirection] = (),
                end_of_stream: bool = False, broken_off: bool = False,
                speech_until_ns: int = 0) -> int: ...

    def forward(self, topic: str, audio: Audio, **meta: Any) -> int: ...

    def emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None,
             **payload: Any) -> pb.Result: ...

    def clock_ns(self) -> int: ...

    def announce_stream(self, start_ns: int, stream_id: str | None = None, **info: Any) -> None: ...

    def join_stream(self, stream_id: str, replay: bool) -> None: ...

    def wait_for_subscribers(self, topic: str, count: int, timeout_s: float) -> bool: ...

    def subscribers(self, topic: str) -> int: ...

    def sleep_until(self, deadline_monotonic: float) -> None: ...

    def stats(self) -> dict[str, Any]: ...

log = logging.getLogger(__name__)


class SetupError(Exception):
    """A component could not be configured (model missing, device unknown...)."""


class Processor:
    """Subclass it, set ``service`` and ``kind``, declare topics, override handlers."""

    service: ClassVar[str] = "component"
    kind: ClassVar[str] = "other"  # the kind of result it produces (e.g. "emotion", "rate"), or "other": none
    # kind's old name: read, it is kind; a subclass that sets it (not kind) still works until the next
    # release, with a deprecation line
    designation: ClassVar[str] = "other"
    Settings: ClassVar[type[ComponentSettings]] = ComponentSettings
    options: ClassVar[dict[str, str]] = {}  # settings that get a command-line flag: name -> help

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "designation" in cls.__dict__ and "kind" not in cls.__dict__:
            log.warning("%s sets designation = %r: its name is kind now (designation is read until the next "
                        "release)", cls.__name__, cls.designation)
            cls.kind = cls.designation
        if cls.kind != "other" and not valid_kind(cls.kind):
            raise TypeError(f"{cls.__name__}.kind {cls.kind!r} is not a kind name (lower case, digits, _)")
        cls.designation = cls.kind

    def __init__(self, settings: ComponentSettings):
        self.settings = settings
        self.inputs: dict[str, AudioFormat] = {}
        self.outputs: dict[str, AudioFormat] = {}
        # this instance of its service (the name): unique while it lives, ours unless set
        self.instance_id = settings.instance or f"{settings.name}-{uuid.uuid4().hex[:8]}"
        self.info: dict[str, Any] = {}  # reported with every heartbeat
        self.context: ProcessorContext | None = None  # given by the runtime that runs this processor

    # -- declaration -----------------------------------------------------------------
    def add_input(self, topic: str, fmt: AudioFormat) -> None:
        self.inputs[topic] = fmt

    def add_output(self, topic: str, fmt: AudioFormat) -> None:
        self.outputs[topic] = fmt

    # -- hooks to override -----------------------------------------------------------
    def setup(self) -> None:
        """Load models, open devices. Raise SetupError with a clear message on failure."""

    def on_audio(self, audio: Audio) -> None:
        """Every received chunk, first."""

    def on_ssl(self, audio: Audio) -> None:
        """A chunk that carries SSL directions, after on_audio."""

    def on_segment_end(self, audio: Audio) -> None:
        """The last chunk of an utterance, after on_audio and on_ssl."""

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """Every input has ended ``stream_id``. By default, end it on every output too."""
        for topic in self.outputs:
            self._context().publish(topic, b"", audio.end_ns, audio.end_ns, stream_id=stream_id, end_of_stream=True)

    def on_command(self, command: Command) -> None:
        """An order from the orchestrator (esiaf/control_messages.py, Command: a player's say, play, stop
        and barge-in), on the data thread between other handlers. By default it is logged and ignored."""
        log.warning("ignored a command order=%s stream_id=%s: %s takes none", command.order.action,
                    command.stream_id, self.service)

    def stream_inputs(self) -> set[str]:
        """The inputs whose end ends a stream here: every input, unless a processor says otherwise (an echo
        canceller's reference may never end)."""
        return set(self.inputs)

    def produce(self) -> None:
        """Sources override this with their capture loop; consumers leave it alone."""
        raise NotImplementedError

    def refresh_info(self) -> None:
        """Before each heartbeat: bring ``info`` up to date, if it reports something computed."""

    def teardown(self) -> None:
        """Release what setup took."""

    def _context(self) -> ProcessorContext:
        if self.context is None:
            raise RuntimeError(f"{type(self).__name__}: no runtime runs it yet (esiaf.node or esiaf.testing)")
        return self.context

    @classmethod
    def produces(cls) -> bool:
        """Whether it is a source (it overrides :meth:`produce`)."""
        return cls.produce is not Processor.produce

"""The component: a processor (esiaf/processor.py) with its context's actions as its own methods.

Every built-in service subclasses :class:`Component`: ``self.publish(...)``, ``self.emit(...)``,
``self.stopping`` and the rest are its context's (esiaf/node.py), and :meth:`Component.run` runs
it in a node of its own, with the processors its ``guests`` setting names beside it
(esiaf/hosting.py). A new analyser needs none of this: it subclasses
:class:`esiaf.UtteranceAnalyser` and implements ``analyse``.
"""
from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from esiaf.audio import Audio
from esiaf.control import ControlClient
from esiaf.formats import AudioFormat
from esiaf.links import OutputStats
from esiaf.node import Context
from esiaf.processor import Processor, SetupError
from esiaf.proto import esiaf_pb2 as pb
from esiaf.receiving import InputStats
from esiaf.settings import ComponentSettings

__all__ = ["Component", "SetupError"]


class Component(Processor):
    """Subclass it, set ``service`` and ``kind``, declare topics, override handlers."""

    context: Context

    def __init__(self, settings: ComponentSettings):
        super().__init__(settings)
        self.context = Context(self)  # its counters exist before it runs (a node takes this context)

    def add_input(self, topic: str, fmt: AudioFormat) -> None:
        super().add_input(topic, fmt)
        self.context.declared()

    def add_output(self, topic: str, fmt: AudioFormat) -> None:
        super().add_output(topic, fmt)
        self.context.declared()

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """Every input has ended ``stream_id``. By default, end it on every output too (``self.publish``)."""
        for topic in self.outputs:
            self.publish(topic, b"", audio.end_ns, audio.end_ns, stream_id=stream_id, end_of_stream=True)

    def run(self) -> int:
        """Set up, register, process until stopped (with its guests); returns the exit code."""
        from esiaf.hosting import hosting_node
        return hosting_node(self).run()

    # -- its context's actions and counters (esiaf/node.py) ----------------------------
    @property
    def stopping(self) -> bool:
        return self.context.stopping

    def stop(self, exit_code: int = 0) -> None:
        self.context.stop(exit_code)

    def publish(self, topic: str, audio: bytes | np.ndarray, start_ns: int, end_ns: int, *,
                stream_id: str | None = None, segmentation_ended: bool = False,
                segment: tuple[int, int] | None = None, ssl_directions: Iterable[pb.SslDirection] = (),
                end_of_stream: bool = False, broken_off: bool = False,
                speech_until_ns: int = 0) -> int:
        """See :meth:`esiaf.node.Context.publish`."""
        return self.context.publish(topic, audio, start_ns, end_ns, stream_id=stream_id,
                                    segmentation_ended=segmentation_ended, segment=segment,
                                    ssl_directions=ssl_directions, end_of_stream=end_of_stream,
                                    broken_off=broken_off, speech_until_ns=speech_until_ns)

    def forward(self, topic: str, audio: Audio, **meta: Any) -> int:
        return self.context.forward(topic, audio, **meta)

    def emit(self, kind: str, span: tuple[int, int], *, stream_id: str | None = None,
             **payload: Any) -> pb.Result:
        return self.context.emit(kind, span, stream_id=stream_id, **payload)

    def clock_ns(self) -> int:
        return self.context.clock_ns()

    def announce_stream(self, start_ns: int, stream_id: str | None = None, **info: Any) -> None:
        self.context.announce_stream(start_ns, stream_id, **info)

    def join_stream(self, stream_id: str, replay: bool) -> None:
        self.context.join_stream(stream_id, replay)

    def wait_for_subscribers(self, topic: str, count: int, timeout_s: float) -> bool:
        return self.context.wait_for_subscribers(topic, count, timeout_s)

    def subscribers(self, topic: str) -> int:
        return self.context.subscribers(topic)

    def sleep_until(self, deadline_monotonic: float) -> None:
        self.context.sleep_until(deadline_monotonic)

    def stats(self) -> dict[str, Any]:
        return self.context.stats()

    @property
    def control(self) -> ControlClient | None:
        return self.context.control

    @property
    def input_stats(self) -> dict[str, InputStats]:
        return self.context.input_stats

    @property
    def output_stats(self) -> dict[str, OutputStats]:
        return self.context.output_stats

    @property
    def refused(self) -> dict[str, int]:
        return self.context.refused

    @property
    def refused_by_publisher(self) -> dict[str, int]:
        return self.context.refused_by_publisher

    @property
    def refused_subscribers(self) -> dict[str, int]:
        return self.context.refused_subscribers

    @property
    def results_sent(self) -> int:
        return self.context.results_sent

    @property
    def results_dropped(self) -> int:
        return self.context.results_dropped

"""What the Wyoming sessions (server.py, on the asyncio thread) hand the node's thread (service.py): a
stream's start, and its audio converted to what the service publishes."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from esiaf import AudioFormat

PUBLISHED = AudioFormat(16_000, "int16", channels=1)  # what the recogniser and the vad take without conversion


@dataclass
class Started:
    """A session's audio starts: announce its stream. ``on_voice``, if given, is called (on the node's thread)
    with "started" or "stopped" and the milliseconds since the stream's start as the vad hears speech."""
    stream_id: str
    info: dict[str, Any]
    on_voice: Callable[[str, int], None] | None = None


@dataclass
class Chunk:
    """A session's converted audio (PUBLISHED); ``last``: its stream ends with it."""
    stream_id: str
    samples: np.ndarray
    last: bool = False

"""What the Wyoming sessions (server.py, on the asyncio thread) hand the node's thread (service.py): a
stream's start, and its audio converted to what the service publishes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from esiaf import AudioFormat

PUBLISHED = AudioFormat(16_000, "int16", channels=1)  # what the recogniser and the vad take without conversion


@dataclass
class Started:
    """A session's audio starts: announce its stream."""
    stream_id: str
    info: dict


@dataclass
class Chunk:
    """A session's converted audio (PUBLISHED); ``last``: its stream ends with it."""
    stream_id: str
    samples: np.ndarray
    last: bool = False

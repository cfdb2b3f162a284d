"""Utterance features shared in a process: computed once per utterance, whoever asks for them.

Several utterance analysers often need the same features of the same utterance (the emotion and
gender services both classify openSMILE ComParE functionals). When they run in one process (a
host and its guests, ``esiaf/hosting.py``), each asks the process's *shared extractor* of that
name, and the first to ask about an utterance computes the features; the others get the same
vector back. Nothing couples the analysers: each still calls its extractor on its own samples,
alone or hosted, and gets exactly what the extractor returns for them.

    from esiaf.features import shared

    prosody = shared("eGeMAPSv02@16000", lambda: MyExtractor("eGeMAPSv02"))  # made once per process
    vector = prosody(samples)  # computed the first time these samples are asked about, then reused

An utterance is known by its samples' bytes (the same audio gives the same features, whatever
stream or span it came from); the last few are kept.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Generic, TypeVar, cast

import numpy as np

KEPT = 8  # utterances remembered per extractor: a host's analysers ask one after the other

E = TypeVar("E", bound=Callable[[np.ndarray], np.ndarray])  # an extractor: samples -> feature vector


class SharedExtractor(Generic[E]):
    """An extractor (samples -> feature vector) whose answers for recent utterances are reused."""

    def __init__(self, name: str, extractor: E):
        self.name = name
        self.extractor = extractor  # what computes: its own attributes (size, names...) stay reachable
        self.computed = 0  # utterances computed
        self.reused = 0  # answers given from what was computed before
        self._recent: OrderedDict[tuple[str, tuple[int, ...], bytes], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def __call__(self, samples: np.ndarray) -> np.ndarray:
        key = (samples.dtype.str, samples.shape, np.ascontiguousarray(samples).tobytes())
        with self._lock:
            vector = self._recent.get(key)
            if vector is not None:
                self._recent.move_to_end(key)
                self.reused += 1
                return vector
            vector = np.asarray(self.extractor(samples))
            vector.flags.writeable = False  # one array for every analyser: none may change it for the others
            self.computed += 1
            self._recent[key] = vector
            while len(self._recent) > KEPT:
                self._recent.popitem(last=False)
            return vector

    def counts(self) -> dict[str, int]:
        return {"computed": self.computed, "reused": self.reused}


_SHARED: dict[str, SharedExtractor[Any]] = {}
_SHARED_LOCK = threading.Lock()


def shared(name: str, make: Callable[[], E]) -> SharedExtractor[E]:
    """The process's extractor called ``name``: made with ``make()`` the first time it is asked for
    (an exception from ``make`` reaches the caller, and the next caller tries again)."""
    with _SHARED_LOCK:
        if name not in _SHARED:
            _SHARED[name] = SharedExtractor(name, make())
        return cast(SharedExtractor[E], _SHARED[name])


def feature_counts() -> dict[str, Any]:
    """Per shared extractor of this process: utterances computed and answers reused."""
    with _SHARED_LOCK:
        return {name: extractor.counts() for name, extractor in _SHARED.items()}

"""A component's signals: SIGTERM and SIGINT stop it, SIGHUP reads the allowed CURVE keys again."""
from __future__ import annotations

import signal
import threading
from collections.abc import Callable


def install(stop: Callable[[], None], reload_keys: Callable[[], None]) -> None:
    """Routes the signals to ``stop`` and ``reload_keys`` (only the main thread may; elsewhere, nothing)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop())
    signal.signal(signal.SIGHUP, lambda *_: reload_keys())

"""Clean stop on SIGINT/SIGTERM: services loop until the event is set, then leave their ``with``."""

from __future__ import annotations

import signal
import threading
from types import FrameType


def stop_on_signals(*wake: threading.Event) -> threading.Event:
    """The event SIGINT and SIGTERM set; ``wake``: events set with it, so that a loop blocked
    waiting on one of them notices the stop at once."""
    stop = threading.Event()

    def _handler(signum: int, frame: FrameType | None) -> None:
        stop.set()
        for event in wake:
            event.set()

    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)
    return stop

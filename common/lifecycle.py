"""Clean stop on SIGINT/SIGTERM: services loop until the event is set, then leave their ``with``.

``catch_stop_signals`` is installed first thing (services.cli, before the heavy imports): a stop
that arrives while the process is still starting (importing OpenCV or MuJoCo, opening its session)
is then an immediate exit 0 (nothing is open yet that needs closing), not a KeyboardInterrupt
traceback or a death by SIGTERM. Once a service
calls ``stop_on_signals`` the signals only set its stop event, which its loops watch."""

from __future__ import annotations

import os
import signal
import threading
from types import FrameType

_stop = threading.Event()
_wake: list[threading.Event] = []
_claimed = False


def _handler(signum: int, frame: FrameType | None) -> None:
    if not _claimed:
        # Nothing runs yet that could stop by itself. Not SystemExit: raised inside an
        # extension module's initialisation it becomes an ImportError traceback.
        os._exit(0)
    _stop.set()
    for event in _wake:
        event.set()


def catch_stop_signals() -> None:
    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)


def stop_on_signals(*wake: threading.Event) -> threading.Event:
    """The event SIGINT and SIGTERM set; ``wake``: events set with it, so that a loop blocked
    waiting on one of them notices the stop at once."""
    global _claimed
    _wake.extend(wake)
    _claimed = True
    catch_stop_signals()
    return _stop


def wait_for_stop(timeout_s: float) -> bool:
    """Whether SIGINT or SIGTERM came within ``timeout_s`` (for a wait before the service's
    own loops run: a signal before ``stop_on_signals`` already ends the process)."""
    return _stop.wait(timeout_s)

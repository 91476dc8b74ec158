"""Clean stop on SIGINT/SIGTERM: services loop until the event is set, then leave their ``with``.

``catch_stop_signals`` is installed first thing (services.cli, before the heavy imports): a stop
that arrives while the process is still starting (importing OpenCV or MuJoCo, opening its session)
is then an immediate exit 0 (nothing is open yet that needs closing), not a KeyboardInterrupt
traceback or a death by SIGTERM. Once a service calls ``stop_on_signals`` the signals only set its
stop event, which its loops watch: from a thread of its own, never from the handler itself. A
handler runs in the main thread between two of its bytecodes, and ``Event.set`` takes the event's
lock, which the main thread may hold at that moment (inside its own ``stop.wait``, or inside the
handler of a first signal when a second arrives: GNU ``timeout`` sends two, microseconds apart):
the service then hung for good."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from types import FrameType

_stop = threading.Event()
_wake: list[threading.Event] = []
_signalled_fd: int | None = None
"""The write end of the pipe the handler writes a byte to for each stop signal, once claimed."""


def _handler(signum: int, frame: FrameType | None) -> None:
    if _signalled_fd is None:
        # Nothing runs yet that could stop by itself. Not SystemExit: raised inside an
        # extension module's initialisation it becomes an ImportError traceback.
        os._exit(0)
    # A full pipe holds earlier signals' bytes unread: the stop is on its way already.
    with contextlib.suppress(BlockingIOError):
        os.write(_signalled_fd, b"\0")


def _set_on_signal(read_fd: int) -> None:
    """The stop thread: sets the events once a signal's byte arrives."""
    os.read(read_fd, 1)
    _stop.set()
    for event in _wake:
        event.set()


def catch_stop_signals() -> None:
    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)


def stop_on_signals(*wake: threading.Event) -> threading.Event:
    """The event SIGINT and SIGTERM set; ``wake``: events set with it, so that a loop blocked
    waiting on one of them notices the stop at once."""
    global _signalled_fd
    _wake.extend(wake)
    if _signalled_fd is None:
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        threading.Thread(
            target=_set_on_signal, args=(read_fd,), name="stop-signals", daemon=True
        ).start()
        _signalled_fd = write_fd
    catch_stop_signals()
    return _stop


def wait_for_stop(timeout_s: float) -> bool:
    """Whether SIGINT or SIGTERM came within ``timeout_s`` (for a wait before the service's
    own loops run: a signal before ``stop_on_signals`` already ends the process)."""
    return _stop.wait(timeout_s)

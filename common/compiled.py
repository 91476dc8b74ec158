"""numba's ``njit`` as the services use it: typed for mypy, cached on disk. Only the services with
loops numpy cannot vectorise import this (fusion's per-cell rules, depth's row scans); the robot
client never does, so its install needs no numba."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar, cast

import numba

Function = TypeVar("Function", bound=Callable[..., object])


def compiled(function: Function) -> Function:
    """``numba.njit``, cached beside the module, in the user's cache or in ``NUMBA_CACHE_DIR`` so a
    restart does not compile again; where none is writable, numba refuses to cache and each process
    compiles once instead (under a second)."""
    try:
        return cast(Function, numba.njit(cache=True, nogil=True)(function))
    except RuntimeError:  # "cannot cache function …: no locator available"
        return cast(Function, numba.njit(nogil=True)(function))

"""The environment ROS 2's PyPI wheels need, set by the command itself.

The wheels install ROS's C libraries into the virtual environment: the dynamic loader must find
them (``LD_LIBRARY_PATH``, read once at process start, so setting it means re-executing this
process) and ament's resource index must name the environment (``AMENT_PREFIX_PATH``, read when
rclpy looks up the middleware and type support, so setting it before the import is enough). The
wheels' own ``ros-wheels-bootstrapper`` already re-executes every Python of the environment with
the first; this covers a bare install without it, and both are no-ops on a robot whose system ROS
2 was sourced.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

REEXEC_GUARD = "OVERGRID_ROS_ENV"


def _prepend(value: str, parts: list[str]) -> str:
    present = [p for p in value.split(os.pathsep) if p]
    return os.pathsep.join([p for p in parts if p not in present] + present)


def ros_environment(environ: Mapping[str, str], prefix: Path) -> dict[str, str]:
    """The variables to change so the wheels under ``prefix`` load; empty when nothing is due."""
    changes: dict[str, str] = {}
    if (prefix / "share" / "ament_index").is_dir():
        ament = _prepend(environ.get("AMENT_PREFIX_PATH", ""), [str(prefix)])
        if ament != environ.get("AMENT_PREFIX_PATH", ""):
            changes["AMENT_PREFIX_PATH"] = ament
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}"
    libs = [str(p) for p in sorted((site / "site-packages").glob("ros_*.libs"))]
    if libs:
        ld = _prepend(environ.get("LD_LIBRARY_PATH", ""), [str(prefix / "lib"), *libs])
        if ld != environ.get("LD_LIBRARY_PATH", ""):
            changes["LD_LIBRARY_PATH"] = ld
    return changes


def ensure_ros_environment() -> None:
    """Set what is missing; re-execute once if the loader's path had to change."""
    changes = ros_environment(os.environ, Path(sys.prefix))
    os.environ.update(changes)
    if "LD_LIBRARY_PATH" in changes and not os.environ.get(REEXEC_GUARD):
        os.environ[REEXEC_GUARD] = "1"
        os.execve(sys.executable, sys.orig_argv, os.environ)

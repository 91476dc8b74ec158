"""Open a Zenoh session from the shared flags, following zenoh-python's own conventions.

No flag at all gives a peer that finds others on this machine or LAN by multicast scouting.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from common.settings import ZenohSettings, startup_error


def zenoh_reason(error: Exception) -> str:
    """Zenoh's message on one line, without the source location of the library's build (a JSON5
    parse error comes as a multi-line pointer: keep its position and its "= expected …" line)."""
    lines = [line.strip(" |") for line in str(error).split(" at /", 1)[0].splitlines()]
    lines = [line for line in lines if line and set(line) - set("^-0123456789 ")]
    return " ".join(line.removeprefix("= ") for line in lines)


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    config_path = settings.config or os.environ.get("ZENOH_CONFIG")
    try:
        return _config(settings, config_path)
    except zenoh.ZError as error:
        where = f"--config / ZENOH_CONFIG {config_path}" if config_path else "Zenoh settings"
        startup_error(f"{where}: {zenoh_reason(error)}")


def _config(settings: ZenohSettings, config_path: str | os.PathLike[str] | None) -> zenoh.Config:
    config = zenoh.Config.from_file(str(config_path)) if config_path else zenoh.Config()
    if settings.mode or not config_path:
        config.insert_json5("mode", json.dumps(settings.mode or "peer"))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.no_multicast_scouting:
        config.insert_json5("scouting/multicast/enabled", "false")
    if settings.namespace:
        config.insert_json5("namespace", json.dumps(settings.namespace))
    return config


@contextmanager
def open_session(settings: ZenohSettings) -> Iterator[zenoh.Session]:
    """A session, or one line and exit 2 when the configuration cannot open one (a bad endpoint,
    a port already in use)."""
    config = zenoh_config(settings)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as error:
        startup_error(f"cannot open the Zenoh session: {zenoh_reason(error)}")
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]

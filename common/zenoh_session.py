"""Open a Zenoh session from the shared flags, following zenoh-python's own conventions.

No flag at all gives a peer that finds others on this machine or LAN by multicast scouting.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from common.settings import ZenohSettings


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    config_path = settings.config or os.environ.get("ZENOH_CONFIG")
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
    session = zenoh.open(zenoh_config(settings))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]

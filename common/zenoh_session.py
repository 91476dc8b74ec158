"""Open a Zenoh session from the shared flags, following zenoh-python's own conventions.

No flag at all gives a peer that finds others on this machine or LAN by multicast scouting.
"""

from __future__ import annotations

import json
import logging
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


CONFIG_FILES = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_certificate",
    "transport/link/tls/connect_private_key",
    "transport/auth/usrpwd/dictionary_file",
)
"""Files a Zenoh config names (TLS, credentials): checked here, since Zenoh's own errors for a
missing one do not name it ("Invalid TLS certificate file: No such file or directory"), and for
a client's certificate blame the network ("Unable to connect to any of [tls/…]")."""


def zenoh_config(settings: ZenohSettings, *, timestamping: bool = False) -> zenoh.Config:
    """The session's configuration; ``timestamping`` stamps every sample with the session's
    clock, as an advanced publisher with a cache and no miss detection needs (rmw_zenoh turns
    it on for every session: a best-effort transient_local topic)."""
    config_path = settings.config or os.environ.get("ZENOH_CONFIG")
    where = f"--config / ZENOH_CONFIG {config_path}" if config_path else "Zenoh settings"
    try:
        config = _config(settings, config_path)
        if timestamping:
            config.insert_json5("timestamping/enabled", "true")
    except zenoh.ZError as error:
        startup_error(f"{where}: {zenoh_reason(error)}")
    for key in CONFIG_FILES:
        try:
            named = json.loads(config.get_json(key))
        except zenoh.ZError:  # no such setting in this Zenoh's schema: nothing to check
            continue
        if isinstance(named, str) and not os.path.isfile(named):
            startup_error(f"{where}: {key} {named}: no such file")
    return config


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
def open_session(settings: ZenohSettings, *, timestamping: bool = False) -> Iterator[zenoh.Session]:
    """A session, or one line and exit 2 when the configuration cannot open one (a bad endpoint,
    a port already in use)."""
    config = zenoh_config(settings, timestamping=timestamping)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as error:
        startup_error(f"cannot open the Zenoh session: {zenoh_reason(error)}")
    try:
        yield session
    finally:
        try:
            session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as error:
            # "close operation timed out" (seen at the end of a recording, with a router's
            # link still draining): the process is ending anyway; the service's own end stands.
            logging.getLogger("overgrid.zenoh").warning(
                "session close failed", extra={"error": zenoh_reason(error)}
            )

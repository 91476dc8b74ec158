"""Open a Zenoh session from the shared flags, following zenoh-python's own conventions.

No flag at all gives a peer that finds others on this machine or LAN by multicast scouting.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import zenoh

from common.lifecycle import wait_for_stop
from common.logs import Transitions
from common.setting_files import setting_file_text
from common.settings import ZenohSettings, startup_error
from common.zenoh_diagnosis import TLS_KEY, certificate_problem, probe_endpoints

log = logging.getLogger("overgrid.zenoh")
ROUTER_RETRY_S = 2.0
ROUTER_WAIT_LOG_S = 10.0
"""A service waiting for its router tries every 2 s and says so every 10 s."""
ROUTER_CHECK_S = 0.2
"""How often a session looks for its router, to log losing and finding it (a cheap call): at 1 s
the lines lagged the link by up to a second, and said "lost" after it was back."""
RECONNECT_RETRY = "{period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2}"
"""``connect/retry`` unless the config file sets it: a session that lost its router tries again
0.1, 0.3, 0.7 s after, then every 0.5 s. Zenoh's default (1 s, doubling to 4 s: tries 1, 3, 7,
11 s after) kept every box off the map until 3 s after a router down 1.5–2.3 s (a systemd
restart at RestartSec=2), 7 s after one down 3.4–4.9 s. The cost: a refused connection every
0.5 s per session meanwhile."""


JSON5_POINTER = re.compile(r"^\s*--> (\d+):(\d+)$")


def zenoh_reason(error: Exception) -> str:
    """Zenoh's message on one line, without the source location of the library's build. A JSON5
    parse error comes as a multi-line pointer (``--> 3:26``, the line, a caret, ``= expected
    boolean or null``): said as line and column, the text there, and the parser's expectation,
    which names what it wanted next, not what is missing (a comma, often, before that place)."""
    text = str(error).split(" at /", 1)[0]
    lines = text.splitlines()
    pointer = JSON5_POINTER.match(lines[0]) if lines else None
    if pointer:
        row, column = pointer.groups()
        source = next(
            (
                line.split("|", 1)[1].strip()
                for line in lines[1:]
                if line.strip().startswith(f"{row} |")
            ),
            "",
        )
        expected = next(
            (line.strip(" |=") for line in lines if line.strip(" |").startswith("=")), ""
        )
        return (
            f"not valid JSON5 at line {row}, column {column} ({source!r}): the parser {expected} "
            "(a comma, colon or bracket missing at or before it reads so too)"
        )
    kept = [line.strip(" |") for line in lines]
    kept = [line for line in kept if line and set(line) - set("^-0123456789 ")]
    return " ".join(line.removeprefix("= ") for line in kept)


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
    config_path = _config_path(settings)
    where = _config_source(settings) or "Zenoh settings"
    if config_path:
        try:  # Zenoh's parser hangs on a pipe and crashes on brackets 60,000 deep
            setting_file_text(Path(config_path))
        except (OSError, ValueError) as error:
            startup_error(f"{where}: {error}")
    try:
        config = _config(settings, config_path)
        if timestamping:
            config.insert_json5("timestamping/enabled", "true")
    except zenoh.ZError as error:
        startup_error(f"{where}: {zenoh_reason(error)}")
    for key in CONFIG_FILES:
        named = _setting(config, key)
        if isinstance(named, str) and not os.path.isfile(named):
            startup_error(f"{where}: {key} {named}: no such file")
    problem = certificate_problem(tls_files(config))
    if problem:
        startup_error(f"{where}: {problem}")
    return config


def _config_path(settings: ZenohSettings) -> str | os.PathLike[str] | None:
    return settings.config or os.environ.get("ZENOH_CONFIG")


def _config_source(settings: ZenohSettings) -> str | None:
    """The config file as an error line names it."""
    config_path = _config_path(settings)
    return f"--config / ZENOH_CONFIG {config_path}" if config_path else None


def _setting(config: zenoh.Config, key: str) -> Any:
    """A setting's value, None where this Zenoh's schema has no such setting."""
    try:
        return json.loads(config.get_json(key))
    except zenoh.ZError:
        return None


def tls_files(config: zenoh.Config) -> dict[str, str]:
    """The TLS files the config names, by setting name (``root_ca_certificate`` → path)."""
    files = {
        key.removeprefix(TLS_KEY): _setting(config, key)
        for key in CONFIG_FILES
        if key.startswith(TLS_KEY)
    }
    return {name: path for name, path in files.items() if isinstance(path, str) and path}


def endpoints(config: zenoh.Config, side: Literal["connect", "listen"]) -> list[str]:
    """The endpoints the session connects to or listens on (a list, or one list per mode)."""
    listed = _setting(config, f"{side}/endpoints")
    if isinstance(listed, dict):
        listed = listed.get(_setting(config, "mode") or "peer", [])
    return [str(endpoint) for endpoint in listed or []]


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
    if _setting(config, "connect/retry") is None:
        config.insert_json5("connect/retry", RECONNECT_RETRY)
    return config


@contextmanager
def open_session(
    settings: ZenohSettings, *, timestamping: bool = False, wait_for_router: bool = False
) -> Iterator[zenoh.Session]:
    """A session, or one line and exit 2 when the configuration cannot open one (a bad endpoint,
    a port already in use, a certificate or password the router refuses: probed, since Zenoh
    names none of them). ``wait_for_router``: a service started before its router waits for it
    (logged every 10 s) instead of exiting; a command run once exits. While the session is open,
    losing the router and finding it again are logged."""
    config = zenoh_config(settings, timestamping=timestamping)
    source = _config_source(settings)
    where = f" ({source})" if source else ""
    connect = endpoints(config, "connect")
    started_s = logged_s = time.monotonic()
    waited = False
    while True:
        try:
            session = zenoh.open(config)
            break
        except zenoh.ZError as error:
            reason = zenoh_reason(error)
            if not reason.startswith("Unable to connect") or not connect:
                startup_error(f"cannot open the Zenoh session{where}: {reason}")
        verify_name = _setting(config, TLS_KEY + "verify_name_on_connect") is not False
        probes = probe_endpoints(connect, tls_files(config), verify_name)
        why = "; ".join(str(probe) for probe in probes)
        # Waiting is for what may pass (a router not up yet, a session refused for a reason
        # the probe can only guess); a certificate refused will not.
        if not wait_for_router or any(probe.definite for probe in probes):
            startup_error(f"cannot reach the Zenoh router{where}: {why}")
        now = time.monotonic()
        if not waited or now - logged_s >= ROUTER_WAIT_LOG_S:
            log.warning(
                "waiting for the Zenoh router",
                extra={"waited_s": round(now - started_s), "why": why},
            )
            logged_s, waited = now, True
        if wait_for_stop(ROUTER_RETRY_S):
            raise SystemExit(0) from None
    if waited:
        log.info(
            "connected to the Zenoh router", extra={"waited_s": round(time.monotonic() - started_s)}
        )
    watching = threading.Event()
    watch = threading.Thread(
        target=_watch_router, args=(session, watching), name="zenoh-router-watch", daemon=True
    )
    if connect:
        watch.start()
    try:
        yield session
    finally:
        watching.set()
        if watch.is_alive():
            watch.join(2 * ROUTER_CHECK_S)
        try:
            session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as error:
            # "close operation timed out" (seen at the end of a recording, with a router's
            # link still draining): the process is ending anyway; the service's own end stands.
            log.warning("session close failed", extra={"error": zenoh_reason(error)})


def _watch_router(session: zenoh.Session, stop: threading.Event) -> None:
    """Log the router's loss and its return: Zenoh reconnects by itself, silently, and meanwhile a
    service would go on counting frames nobody receives."""
    router = Transitions(
        log,
        "lost the Zenoh router: reconnecting",
        "reconnected to the Zenoh router",
        "connected to the Zenoh router",
        right=bool(session.info.routers_zid()),
    )
    while not stop.wait(ROUTER_CHECK_S):
        try:
            router.update(bool(session.info.routers_zid()))
        except zenoh.ZError:  # closing
            return

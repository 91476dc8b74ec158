"""``overgrid router``: a Zenoh router for sites where multicast scouting does not cross subnets.

No zenohd is installable here, so a Zenoh session in router mode serves: every service on another
box then takes ``--connect tcp/ROUTER:7447`` (or a config file with TLS, credentials and, on the
router, the access-control rules of ``deploy/zenoh/``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Literal

from pydantic import Field

from common.lifecycle import stop_on_signals
from common.logs import setup_logging
from common.settings import ZenohSettings, parse_settings
from common.zenoh_session import endpoints, open_session, zenoh_config

log = logging.getLogger("router")


DEFAULT_LISTEN = "tcp/[::]:7447"


class RouterSettings(ZenohSettings):
    mode: Literal["peer", "client", "router"] | None = Field(
        "router", description="Zenoh session mode"
    )


def main(settings: RouterSettings) -> None:
    setup_logging("router", settings.log_level)
    stop = stop_on_signals()
    if not settings.listen and not settings.config:  # a config file brings its own endpoints
        settings = settings.model_copy(update={"listen": [DEFAULT_LISTEN]})
    with open_session(settings) as session:
        log.info(
            "started",
            extra={
                "zid": str(session.zid()),
                "listen": ",".join(endpoints(zenoh_config(settings), "listen")),
                "config": str(settings.config or ""),
            },
        )
        stop.wait()
    log.info("stopped")


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            RouterSettings,
            argv,
            "overgrid router",
            "A Zenoh router: the meeting point of services on other subnets or boxes.",
        )
    )

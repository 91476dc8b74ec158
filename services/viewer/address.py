"""Where the page is served: defaults, a port that is free, the URL to print. Light on purpose:
``overgrid up`` imports it without the web framework."""

from __future__ import annotations

import errno
import socket
from urllib.parse import quote

DEFAULT_HTTP_HOST = "127.0.0.1"
"""Loopback: the page is private to this box unless --http-host says otherwise."""
DEFAULT_HTTP_PORT = 8470
LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


def available_port(host: str, preferred: int) -> int:
    """``preferred`` if nothing listens there yet, else any free port (another `up` may hold it)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    for port in (preferred, 0):
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            try:
                probe.bind((host, port))
            except OSError as error:
                if error.errno != errno.EADDRINUSE or port == 0:
                    raise
                continue
            return int(probe.getsockname()[1])
    raise AssertionError("unreachable")


def page_url(host: str, port: int, token: str | None = None) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/" + (f"?token={quote(token)}" if token else "")

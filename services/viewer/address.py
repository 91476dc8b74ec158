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


ALL_INTERFACES = frozenset({"0.0.0.0", "", "::"})


def page_url(host: str, port: int, token: str | None = None) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/" + (f"?token={quote(token)}" if token else "")


def lan_addresses() -> list[str]:
    """This box's IPv4 addresses other than loopback, the one its default route leaves by first
    (a UDP socket "connected" to a documentation address sends nothing): what a page served on
    every interface is opened at from another box. Empty on a box with no network."""
    found: list[str] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: routed like the LAN, never answered
            found.append(str(probe.getsockname()[0]))
        except OSError:
            pass
    try:
        named = socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)
    except OSError:
        named = []
    found += [str(info[4][0]) for info in named]
    return [a for a in dict.fromkeys(found) if not a.startswith(("127.", "0."))]


def page_urls(host: str, port: int, token: str | None = None) -> list[str]:
    """The URLs to print: the page's, and on every interface also the LAN's (the loopback one
    opens the page on this box only)."""
    urls = [page_url(host, port, token)]
    if host in ALL_INTERFACES:
        urls += [page_url(address, port, token) for address in lan_addresses()]
    return urls

"""Why a Zenoh session will not open, in words a site can act on.

Zenoh reports every refused connection alike ("Unable to connect to any of [tls/…]"): a router
that is down, a wrong password, an expired or foreign certificate, a host name the certificate
does not carry. So the TLS files a config names are checked at start-up (dates, key against
certificate), and a refused connection is probed with Python's own socket and TLS stack, which
say which of those it was. No Zenoh here: endpoints and file paths in, one line out.
"""

from __future__ import annotations

import contextlib
import socket
import ssl
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from common.settings import endpoint_parts

TLS_KEY = "transport/link/tls/"
CERTIFICATES = ("root_ca_certificate", "listen_certificate", "connect_certificate")
KEY_PAIRS = (
    ("listen_certificate", "listen_private_key"),
    ("connect_certificate", "connect_private_key"),
)
PROBE_TIMEOUT_S = 3.0
"""How long a probe waits for a connection, and then for the router's word on the certificate."""
ALERT_PREFIXES = ("SSLV3_ALERT_", "TLSV1_ALERT_", "TLSV13_ALERT_")


def certificate_problem(tls: Mapping[str, str], now_s: float | None = None) -> str | None:
    """What is wrong with the TLS files ``tls`` (Zenoh's ``transport/link/tls`` settings: name →
    path) before any connection: a certificate expired or not yet valid, a key that is not its
    certificate's. None when nothing is. An expired router certificate otherwise starts a
    router that refuses every box with the generic line."""
    now_s = time.time() if now_s is None else now_s
    decode = getattr(ssl, "_ssl", None) and getattr(ssl._ssl, "_test_decode_cert", None)  # type: ignore[attr-defined]
    for name in CERTIFICATES:
        path = tls.get(name)
        if not path or decode is None:
            continue
        try:
            fields = decode(path)
        except (ssl.SSLError, OSError) as error:
            return f"{TLS_KEY}{name} {path}: not a PEM certificate ({error})"
        if now_s > ssl.cert_time_to_seconds(fields["notAfter"]):
            return f"{TLS_KEY}{name} {path}: expired on {fields['notAfter']}"
        if now_s < ssl.cert_time_to_seconds(fields["notBefore"]):
            return (
                f"{TLS_KEY}{name} {path}: not valid before {fields['notBefore']} "
                "(is this box's clock right?)"
            )
    for certificate, key in KEY_PAIRS:
        if tls.get(certificate) and tls.get(key):
            try:
                ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(
                    tls[certificate], tls[key], password=_no_password
                )
            except (ssl.SSLError, OSError) as error:
                reason = getattr(error, "reason", None)
                words = "no private key in it" if reason == "PEM lib" else _words(reason)
                return (
                    f"{TLS_KEY}{key} {tls[key]}: not the key of {certificate} {tls[certificate]} "
                    f"({words or error})"
                )
    return None


def _no_password() -> bytes:
    """An encrypted key's password: none (OpenSSL would ask for one on the terminal, and wait)."""
    return b""


@dataclass(frozen=True)
class Probe:
    """One endpoint probed: ``reason`` in words; ``definite`` when it names a fault of the
    configuration (a certificate refused, an endpoint with no port), not a guess or a state
    that may pass (nothing listening yet, a session refused for a reason the probe cannot see)."""

    endpoint: str
    definite: bool
    reason: str

    def __str__(self) -> str:
        return f"{self.endpoint}: {self.reason}"


def probe_endpoints(
    endpoints: Sequence[str], tls: Mapping[str, str], verify_name: bool = True
) -> list[Probe]:
    return [probe(endpoint, tls, verify_name) for endpoint in endpoints]


def probe(
    endpoint: str,
    tls: Mapping[str, str],
    verify_name: bool = True,
    timeout_s: float = PROBE_TIMEOUT_S,
) -> Probe:
    """Why a session could not open on ``endpoint`` (``tcp/HOST:PORT`` or ``tls/HOST:PORT``);
    ``verify_name``: Zenoh's ``verify_name_on_connect``, whether the router's certificate must
    name the host."""
    protocol, address, host, port = endpoint_parts(endpoint)
    if protocol not in ("tcp", "tls"):
        return Probe(endpoint, False, f"protocol {protocol!r} not probed (tcp or tls?)")
    if ":" not in address or not port.isdigit():
        return Probe(endpoint, True, "no port: an endpoint is PROTOCOL/HOST:PORT")
    host = host.strip("[]")
    try:
        connection = socket.create_connection((host, int(port)), timeout=timeout_s)
    except socket.gaierror as error:
        return Probe(endpoint, False, f"cannot resolve {host} ({error.strerror})")
    except OSError as error:
        why = error.strerror or type(error).__name__
        return Probe(endpoint, False, f"nothing answers ({why}): is the router up at that address?")
    with connection:
        if protocol == "tcp":
            return Probe(endpoint, False, REFUSED_ON_TCP)
        return _tls_probe(endpoint, connection, host, tls, verify_name, timeout_s)


REFUSED_ON_TCP = (
    "the router answers and refused the session: its user and password "
    "(transport/auth/usrpwd), or it wants TLS"
)
REFUSED_ON_TLS = (
    "TLS accepted, then the router refused the session: its user and password "
    "(transport/auth/usrpwd)"
)


def _tls_probe(
    endpoint: str,
    connection: socket.socket,
    host: str,
    tls: Mapping[str, str],
    verify_name: bool,
    timeout_s: float,
) -> Probe:
    ca = tls.get("root_ca_certificate")
    certificate, key = tls.get("connect_certificate"), tls.get("connect_private_key")
    against = (
        f"{TLS_KEY}root_ca_certificate {ca}" if ca else "the system's CAs (no root_ca_certificate)"
    )
    try:
        context = ssl.create_default_context(cafile=ca)
        context.check_hostname = verify_name
        if certificate and key:
            context.load_cert_chain(certificate, key, password=_no_password)
        with context.wrap_socket(connection, server_hostname=host) as link:
            # TLS 1.3: the router judges this box's certificate after the handshake and says so
            # in its first message; silence means it took the certificate.
            link.settimeout(timeout_s)
            with contextlib.suppress(TimeoutError):
                link.recv(1)
    except ssl.SSLCertVerificationError as error:
        return Probe(
            endpoint,
            True,
            f"the router's certificate fails against {against}: {error.verify_message}",
        )
    except (ssl.SSLEOFError, ConnectionError) as error:  # no TLS there, or a link limit
        return Probe(
            endpoint,
            False,
            f"closed during the TLS handshake ({type(error).__name__}): is it a tls/ listener?",
        )
    except ssl.SSLError as error:
        words = _words(error.reason) or str(error)
        if not certificate:
            return Probe(endpoint, True, f"the router wants this box's certificate ({words})")
        return Probe(
            endpoint,
            True,
            f"the router refused this box's certificate {TLS_KEY}connect_certificate "
            f"{certificate}: {words}",
        )
    except OSError as error:
        return Probe(endpoint, False, f"TLS failed: {error}")
    return Probe(endpoint, False, REFUSED_ON_TLS)


def _words(reason: str | None) -> str:
    """OpenSSL's reason code as words: ``SSLV3_ALERT_CERTIFICATE_EXPIRED`` → ``certificate
    expired``."""
    if not reason:
        return ""
    for prefix in ALERT_PREFIXES:
        reason = reason.removeprefix(prefix)
    return reason.replace("_", " ").lower()

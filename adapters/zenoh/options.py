"""Zenoh endpoint and TLS option checks that need no ``zenoh`` import.

The run config (``hil.harness.config.target``) validates with these before anything
starts, and ``hil.adapters.zenoh.link`` applies the same rules when it builds a
session, so a config that can never open a session is refused up front.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping

from hil.common.errors import ConfigError

__all__ = ["AUTH_ENV", "DEFAULT_LEASE_MS", "IP_PROTOCOLS", "PROTOCOLS", "TLS_KEYS", "endpoint_problem", "run_usrpwd", "tls_key_problem",
           "usrpwd_from_env"]

DEFAULT_LEASE_MS = 1000  # a silent peer is gone after this (Zenoh's own default: 10 s)
AUTH_ENV = "HIL_ZENOH_AUTH"  # a run's own user:password, given to the target the harness starts

# Zenoh's link protocols (zenoh 1.10). The IP ones take ``host:port``.
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
PROTOCOLS = (*IP_PROTOCOLS, "unixsock-stream", "unixpipe", "serial", "vsock")
# The keys of Zenoh's ``transport/link/tls`` section this harness passes through.
TLS_KEYS = (
    "root_ca_certificate", "root_ca_certificate_base64",
    "listen_certificate", "listen_certificate_base64",
    "listen_private_key", "listen_private_key_base64",
    "connect_certificate", "connect_certificate_base64",
    "connect_private_key", "connect_private_key_base64",
    "enable_mtls", "verify_name_on_connect", "close_link_on_expiration",
)
_PLACEHOLDERS = ("{port}", "{vehicle_id}")
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.%a-zA-Z]+\]|[^\s:/\[\]]+):(?P<port>\d{1,5})$")


def endpoint_problem(endpoint: object) -> str | None:
    """Why ``endpoint`` can never be a Zenoh endpoint, or None when it can.

    ``{port}`` and ``{vehicle_id}`` count as numbers (they are filled per vehicle).
    The form is ``PROTOCOL/ADDRESS[?metadata][#config]``; an IP protocol's address
    is ``host:port`` with a port in 0..65535 (0: any free port, for listening).
    """
    if not isinstance(endpoint, str):
        return f"a string PROTOCOL/ADDRESS, not {type(endpoint).__name__}"
    proto, sep, rest = endpoint.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if not sep or not proto or not address:
        return "PROTOCOL/ADDRESS, e.g. tcp/192.168.1.10:7447"
    if proto not in PROTOCOLS:
        return f"a known protocol ({', '.join(PROTOCOLS)}), not {proto!r}"
    if proto in IP_PROTOCOLS:
        filled = address
        for p in _PLACEHOLDERS:
            filled = filled.replace(p, "1")
        m = _HOST_PORT.match(filled)
        if m is None:
            return f"{proto}/HOST:PORT, e.g. {proto}/192.168.1.10:7447 (the port is required)"
        if int(m["port"]) > 65535:
            return f"a port in 0..65535, not {m['port']}"
    return None


def tls_key_problem(key: object) -> str | None:
    """Why ``key`` is not a TLS option this harness passes to Zenoh, or None."""
    if key in TLS_KEYS:
        return None
    import difflib

    close = difflib.get_close_matches(str(key), TLS_KEYS, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"a known TLS key{hint}: {', '.join(TLS_KEYS)}"


def run_usrpwd(user: str, password: str) -> dict[str, str]:
    """Zenoh ``usrpwd`` options of a run's own credentials: present them and admit only
    peers that present them too (``dictionary``: the lines, which
    ``hil.adapters.zenoh.session.open_session`` writes to a private file while the session opens).
    Zenoh gives no session to a peer without them, nor to one that asks for other ones."""
    return {"user": user, "password": password, "dictionary": f"{user}:{password}\n"}


def usrpwd_from_env(environ: Mapping[str, str] = os.environ) -> dict[str, str] | None:
    """``run_usrpwd`` of ``AUTH_ENV`` (``user:password``, set by a harness for the target
    it starts), or None when it is not set.

    Raises:
        ConfigError: it is set but not ``user:password``.
    """
    text = environ.get(AUTH_ENV)
    if not text:
        return None
    user, sep, password = text.partition(":")
    if not sep or not user or not password:
        raise ConfigError(f"{AUTH_ENV} must be user:password")
    return run_usrpwd(user, password)

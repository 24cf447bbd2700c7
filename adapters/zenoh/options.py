"""The zenoh transport's options, in one place and with no ``zenoh`` import:
``ZenohOptions`` (both halves' session: endpoints, mode, keys, lease, TLS,
user/password), a run's own keys and credentials (``ZenohOptions.for_run``) and
what a target the harness starts is told (``ZenohOptions.child_env``), a target's
``--tls``/``--auth-dictionary`` (``parse_tls``, ``target_usrpwd``), and the endpoint
and TLS checks.

The run config (``hil.harness.config.target``) validates with these before anything
starts, and ``hil.adapters.zenoh.session`` applies the same rules when it builds a
session, so a config that can never open a session is refused up front.
"""

from __future__ import annotations

import os
import re
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from hil.common.errors import ConfigError

__all__ = ["AUTH_ENV", "DEFAULT_LEASE_MS", "IP_PROTOCOLS", "PREFIX_ENV", "PROTOCOLS", "TLS_KEYS", "ZenohOptions",
           "endpoint_problem", "parse_tls", "run_usrpwd", "target_usrpwd", "tls_key_problem", "usrpwd_from_env"]

DEFAULT_LEASE_MS = 1000  # a silent peer is gone after this (Zenoh's own default: 10 s)
AUTH_ENV = "HIL_ZENOH_AUTH"  # a run's own user:password, given to the target the harness starts
PREFIX_ENV = "HIL_ZENOH_KEY_PREFIX"  # the run's key prefix, given to the target the harness starts

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


def parse_tls(items: Sequence[str]) -> dict[str, str | bool] | None:
    """``transport/link/tls`` options from a target's ``--tls KEY=VALUE`` items
    (``true``/``false`` become booleans), or None for none.

    Raises:
        ConfigError: an item is not ``KEY=VALUE`` with a known key (one line naming it).
    """
    tls: dict[str, str | bool] = {}
    for item in items:
        key, sep, value = item.partition("=")
        problem = "KEY=VALUE, e.g. listen_certificate=dev.pem" if not sep or not key else tls_key_problem(key)
        if problem is not None:
            raise ConfigError(f"--tls {item!r}: expected {problem}")
        tls[key] = {"true": True, "false": False}.get(value.lower(), value)
    return tls or None


def target_usrpwd(dictionary_file: str | None, environ: Mapping[str, str] = os.environ) -> dict[str, str] | None:
    """A target's user/password options: admit only the peers listed in
    ``dictionary_file`` (``--auth-dictionary``), else the run's own credentials a
    harness that started it gave in ``AUTH_ENV`` (``usrpwd_from_env``), else None.

    Raises:
        ConfigError: ``AUTH_ENV`` is set but not ``user:password``.
    """
    if dictionary_file:
        return {"dictionary_file": dictionary_file}
    return usrpwd_from_env(environ)


@dataclass(frozen=True)
class ZenohOptions:
    """A Zenoh session's options, the one home of their defaults: the harness's link
    (``ZenohLink``, a mixed link's ``ZenohHalf``), a target's ``serve_endpoint``, the
    run config (``target.zenoh``) and the target programs' command line read them.

    Attributes:
        connect, listen: Zenoh endpoints (``tcp/host:port``, ``tls/host:port``); a
            session needs at least one. Lists are kept as tuples.
        mode: ``peer`` or ``client``.
        key_prefix: the keys are ``<key_prefix>/v<vehicle>/...`` (``hil.adapters.zenoh.session.Keys``).
        multicast_scouting: off unless asked for (nothing is discovered).
        congestion_control: the harness's puts, ``block`` (nothing dropped silently)
            or ``drop``; a target's answers always block.
        lease_ms: how long a silent peer is waited for before it is gone (ms).
        tls: ``transport/link/tls`` keys (``TLS_KEYS``), or None.
        usrpwd: Zenoh's user/password (``hil.adapters.zenoh.session.USRPWD_KEYS``, or
            ``dictionary``: a run's own lines, ``run_usrpwd``), or None.
        shared_memory: Zenoh's shared-memory transport; None keeps Zenoh's default (on).
    """

    connect: Sequence[str] = ()
    listen: Sequence[str] = ()
    mode: str = "peer"
    key_prefix: str = "hil"
    multicast_scouting: bool = False
    congestion_control: str = "block"
    lease_ms: int = DEFAULT_LEASE_MS
    tls: Mapping[str, object] | None = None
    usrpwd: Mapping[str, str] | None = field(default=None, repr=False)  # a password: never in a repr
    shared_memory: bool | None = None

    def __post_init__(self) -> None:
        for name in ("connect", "listen"):  # a bare string stays one, for the session's check to name
            value = getattr(self, name)
            if not isinstance(value, str):
                object.__setattr__(self, name, tuple(value))

    def for_run(self, *, session: str, vehicle_id: int, credentials: bool) -> ZenohOptions:
        """These options for a run whose harness starts its own target: keys under
        ``<key_prefix>/run-<session>`` (no other target on the endpoint answers for
        it) and, with ``credentials``, user/password made for this run from fresh
        randomness (never the session nonce, which summary.json shows), so a third
        peer gets no session."""
        usrpwd = (run_usrpwd(f"hil-{session}-v{vehicle_id}", secrets.token_urlsafe(24)) if credentials
                  else self.usrpwd)
        return replace(self, key_prefix=f"{self.key_prefix}/run-{session}", usrpwd=usrpwd)

    def child_env(self) -> dict[str, str]:
        """What a target the harness starts is told (the SDK follows both): the key
        prefix (``PREFIX_ENV``) and, where the run made its own, the credentials
        (``AUTH_ENV``, ``user:password``; never written to the run folder)."""
        env = {PREFIX_ENV: self.key_prefix}
        own = self.usrpwd or {}
        if "dictionary" in own:
            env[AUTH_ENV] = f"{own['user']}:{own['password']}"
        return env

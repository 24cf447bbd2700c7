"""The Zenoh session both halves of the zenoh transport open: its configuration
(explicit endpoints, multicast scouting off unless asked for, lease, TLS, user/password),
a bounded close, and the key expressions of one vehicle (``Keys``; the keys, handshake
and liveness are described in ``hil.adapters.zenoh.link``).

Raises: :class:`hil.common.errors.ConfigError` for a bad option,
:class:`hil.common.errors.TransportError` when a session cannot be opened.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from types import MappingProxyType

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import MsgType
from hil.adapters.zenoh.options import TLS_KEYS, ZenohOptions, endpoint_problem
from hil.common.errors import ConfigError, TransportError

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the zenoh transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err

MODES = ("peer", "client")
DEFAULT_KEEP_ALIVE = 4  # keep-alives per lease
BYE_LINGER_S = 1.0  # how long a stopping target waits for the harness to leave after its BYE
USRPWD_KEYS = ("user", "password", "dictionary_file")
CLOSE_TIMEOUT_S = 2.0  # how long closing a session may take (s) before it is left to finish alone
_RETRY = MappingProxyType({"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2})
_WILDCARD_CHARS = frozenset("*$?#")


@dataclass(frozen=True)
class Keys:
    """The key expressions of one vehicle under one prefix (module docstring)."""

    h2t: str
    t2h: str
    alive: str
    harness: str

    @classmethod
    def of(cls, key_prefix: str, vehicle_id: int) -> Keys:
        """Raises ConfigError: the prefix is not a plain key expression or the id is out of range."""
        if not isinstance(vehicle_id, int) or not 0 <= vehicle_id <= 2**32 - 1:
            raise ConfigError(f"vehicle_id={vehicle_id!r}: expected an integer in 0..4294967295")
        if (not key_prefix or key_prefix.startswith("/") or key_prefix.endswith("/")
                or "//" in key_prefix or _WILDCARD_CHARS & set(key_prefix)):
            raise ConfigError(f"key_prefix={key_prefix!r}: expected a plain key expression such as "
                              f"'hil' or 'hil/run-a' (no wildcards, no leading or trailing '/')")
        try:
            zenoh.KeyExpr(key_prefix)
        except zenoh.ZError as err:
            raise ConfigError(f"key_prefix={key_prefix!r} is not a zenoh key expression: {err}") from err
        base = f"{key_prefix}/v{vehicle_id}"
        return cls(f"{base}/h2t", f"{base}/t2h", f"{base}/alive", f"{base}/harness")


def _check_endpoints(name: str, endpoints: Sequence[str]) -> list[str]:
    if isinstance(endpoints, str):
        raise ConfigError(f"{name}={endpoints!r}: expected a list of endpoints, e.g. [{endpoints!r}]")
    out = []
    for ep in endpoints:
        problem = endpoint_problem(ep)
        if problem is not None:
            raise ConfigError(f"{name}: endpoint {ep!r}: expected {problem}")
        out.append(str(ep))
    return out


def config_entries(options: ZenohOptions, *, gossip: bool = False,
                   keep_alive: int = DEFAULT_KEEP_ALIVE) -> dict[str, object]:
    """The Zenoh config of a session with ``options``, as ``{config path: JSON value}``
    (``keep_alive``: keep-alives per lease; ``gossip``: Zenoh's gossip scouting).

    ``options.usrpwd``: Zenoh's user/password authentication (``USRPWD_KEYS``): ``user`` and
    ``password`` to present, ``dictionary_file`` (lines ``user:password``) to accept
    only those peers; or ``dictionary``, the lines themselves, which
    :func:`open_session` writes to a private file only while the session opens (a
    run's own credentials: ``hil.adapters.zenoh.options.run_usrpwd``, ``AUTH_ENV``).

    ``options.lease_ms`` (ms) is how long a peer may stay silent before this session's
    lease runs out at the other end; ``shared_memory`` None keeps Zenoh's default (on).

    Raises:
        ConfigError: a bad mode, endpoint, TLS key or lease (the message names it).
    """
    mode, lease_ms, multicast_scouting = options.mode, options.lease_ms, options.multicast_scouting
    if mode not in MODES:
        raise ConfigError(f"zenoh mode={mode!r}: expected one of {', '.join(MODES)}")
    if not isinstance(lease_ms, int) or lease_ms < 100:
        raise ConfigError(f"zenoh lease_ms={lease_ms!r}: expected an integer number of ms >= 100")
    if not isinstance(keep_alive, int) or keep_alive < 1:
        raise ConfigError(f"zenoh keep_alive={keep_alive!r}: expected an integer >= 1")
    entries: dict[str, object] = {
        "mode": mode,
        "connect/endpoints": _check_endpoints("connect", options.connect),
        "listen/endpoints": _check_endpoints("listen", options.listen),
        "connect/retry": dict(_RETRY),
        "scouting/multicast/enabled": bool(multicast_scouting),
        "scouting/gossip/enabled": bool(gossip),
        "transport/link/tx/lease": lease_ms,
        "transport/link/tx/keep_alive": keep_alive,
    }
    if not multicast_scouting:
        # Without scouting there is nothing to wait for: open() returns at once (else
        # 500 ms) and unreached endpoints are retried in the background (connect/retry).
        entries["scouting/delay"] = 0
    if options.shared_memory is not None:
        entries["transport/shared_memory/enabled"] = bool(options.shared_memory)
    value: object  # a usrpwd value (str), then a tls value
    for key, value in (options.usrpwd or {}).items():
        if key == "dictionary":
            continue  # inline lines: open_session writes them (see above)
        if key not in USRPWD_KEYS:
            raise ConfigError(f"zenoh usrpwd key {key!r} is unknown; valid: {', '.join(USRPWD_KEYS)}")
        entries[f"transport/auth/usrpwd/{key}"] = str(value)
    for key, value in (options.tls or {}).items():
        if key not in TLS_KEYS:
            raise ConfigError(f"zenoh tls key {key!r} is unknown; valid: {', '.join(TLS_KEYS)}")
        entries[f"transport/link/tls/{key}"] = value
    return entries


def make_config(options: ZenohOptions, *, gossip: bool = False, keep_alive: int = DEFAULT_KEEP_ALIVE) -> zenoh.Config:
    """A ``zenoh.Config`` from ``config_entries(options, ...)``; nothing else is
    defaulted from the environment.

    Raises:
        ConfigError: as ``config_entries``, or Zenoh rejects a value.
    """
    cfg = zenoh.Config()
    for key, value in config_entries(options, gossip=gossip, keep_alive=keep_alive).items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except zenoh.ZError as err:
            raise ConfigError(f"zenoh config {key}={value!r} rejected: {err}") from err
    return cfg


def close_session(session: zenoh.Session, *, timeout_s: float = 2.0) -> str | None:
    """Close ``session`` in a daemon thread and wait at most ``timeout_s`` (s) for it.

    Returns None when it closed in time, else why not (it is left closing in the
    background). Never raises: closing must not cost a run its outputs.
    """
    failure: list[str] = []

    def run() -> None:
        try:
            session.close()
        except Exception as err:  # noqa: BLE001 - zenoh.ZError and whatever the binding raises
            failure.append(f"zenoh session close failed: {type(err).__name__}: {err}")

    t = threading.Thread(target=run, name="zenoh-close", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        return f"zenoh session close took over {timeout_s:g} s (a frozen peer?); left closing in the background"
    return failure[0] if failure else None


_RUST_WHERE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")  # " at /root/.cargo/.../unicast.rs:338."


def zenoh_error_text(err: BaseException) -> str:
    """A Zenoh error for a person: without the Rust source locations it carries."""
    return _RUST_WHERE.sub("", str(err)).replace("[", "").replace("]", "").strip()


def open_session(cfg: zenoh.Config, where: str, *, dictionary: str | None = None) -> zenoh.Session:
    """Open a session; ``dictionary`` (lines ``user:password``) is written to a file
    only this user can read, named as ``transport/auth/usrpwd/dictionary_file``, and
    removed once the session is open (Zenoh reads it at open).

    Raises:
        TransportError: the session cannot be opened.
    """
    path = None
    try:
        if dictionary is not None:
            fd, path = tempfile.mkstemp(prefix="hil-zenoh-auth-", suffix=".txt")  # mode 0600
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(dictionary)
            cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(path))
        return zenoh.open(cfg)
    except (zenoh.ZError, OSError) as err:
        raise TransportError(f"cannot open a zenoh session ({where}): {zenoh_error_text(err)}") from err
    finally:
        if path is not None:
            os.unlink(path)


def open_with(options: ZenohOptions) -> zenoh.Session:
    """A session with ``options`` (``make_config``; a run's own credentials written as
    ``open_session`` does), as a target opens one.

    Raises:
        ConfigError: a bad option. TransportError: the session cannot be opened.
    """
    return open_session(make_config(options), f"listen={list(options.listen)} connect={list(options.connect)}",
                        dictionary=(options.usrpwd or {}).get("dictionary"))


def _is(data: bytes, mtype: MsgType) -> bool:
    return len(data) >= protocol.HEADER_SIZE and data[:4] == protocol.MAGIC and data[5] == mtype


__all__ = ["BYE_LINGER_S", "CLOSE_TIMEOUT_S", "DEFAULT_KEEP_ALIVE", "MODES", "USRPWD_KEYS", "Keys", "close_session",
           "config_entries", "make_config", "open_session", "open_with", "zenoh_error_text"]

"""The Zenoh transport: the target is a remote host (or a local process) on a Zenoh network.

Each Zenoh sample carries exactly one encoded protocol message (PROTOCOL.md). A run
uses four key expressions per vehicle, under a key prefix (``key_prefix``, default
``hil``) that both sides are given::

    {prefix}/v{vehicle_id}/h2t      harness -> target: FRAME, SYNC_REQUEST, HEARTBEAT, BYE
    {prefix}/v{vehicle_id}/t2h      target -> harness: HELLO, ESTIMATE, SYNC_RESPONSE, ERROR, BYE
    {prefix}/v{vehicle_id}/alive    liveliness token of the target
    {prefix}/v{vehicle_id}/harness  liveliness token of the harness

One key per direction, because a Zenoh session receives its own publications. One run
drives several targets by vehicle id; two runs on one network keep apart by giving
each its own prefix (``hil/run-a``, ``hil/run-b``).

Handshake. The target's HELLO (sent once by ``Endpoint.start``) may be published
before the harness has subscribed, and is then lost. So the harness, once its
subscribers are declared, publishes a HEARTBEAT on ``h2t`` every 100 ms (and at once
when it sees the target's liveliness token) until a HELLO arrives; ``serve_endpoint``
answers every HEARTBEAT that comes before the first FRAME or SYNC_REQUEST with a
fresh HELLO. The harness keeps the first HELLO and drops the duplicates (counted in
``ZenohLink.zenoh_stats.duplicate_hellos``).

Liveness. The harness subscribes to the target's liveliness token; its DELETE (the
target's session closed, its process died, or its link's lease expired) marks the
link gone. A killed process closes its TCP socket and is noticed in a few ms (3-4 ms
measured on loopback). A silent peer (frozen process, pulled cable) is noticed when
the lease it announced expires: ``transport/link/tx/lease`` is set to ``lease_ms``
(default 1000 ms, Zenoh's own default is 10 s) with a keep-alive every
``lease_ms / keep_alive`` (250 ms), on both sides; a frozen (SIGSTOP) target was
noticed after 0.9 s. It is the silent side's announced lease that counts, so a target
started with Zenoh's defaults would take 10 s. The target likewise stops serving when
the harness's token goes away (as the local transport stops on EOF), so a crashed
harness never leaves it wedged. A target stopped by SIGTERM or Ctrl-C says BYE and
then waits (at most ``BYE_LINGER_S``) for the harness to leave, because its token's
DELETE could otherwise overtake the BYE and read as a crash.

Congestion. Frames are put with ``congestion_control="block"`` by default: Zenoh's
default (DROP) lost hundreds of frames in bursts. BLOCK waits for the queue (at most
Zenoh's ``wait_before_close``, 5 s, after which the link is closed and liveliness is
lost). Under ``"drop"`` Zenoh drops silently, and those frames surface only as
frames without an estimate (the harness counts them as dropped). A put that raises
is counted in ``zenoh_stats.put_failures`` and raised as ``TransportError``.

Network policy. Configs are explicit: multicast scouting and gossip are off unless
asked for, and the session listens and connects only on the endpoints given
(``make_config``). TLS: give ``tls`` a dict of ``transport/link/tls`` keys
(``TLS_KEYS``), for example ``{"root_ca_certificate": "ca.pem"}`` on the harness and
``{"listen_certificate": "dev.pem", "listen_private_key": "dev.key"}`` on the target,
with ``tls/host:port`` endpoints; mutual TLS adds ``enable_mtls: true`` and the
``connect_certificate``/``connect_private_key`` pair on the harness.
"""

from __future__ import annotations

import json
import os
import queue
import re
import tempfile
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

from hil.adapters import protocol, transports
from hil.adapters.link import Link, LinkStats, Received
from hil.adapters.messages import Heartbeat, MsgType
from hil.adapters.zenoh_options import TLS_KEYS, endpoint_problem
from hil.common.errors import ConfigError, TransportError
from hil.timing.clock import Clock

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the zenoh transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint

MODES = ("peer", "client")
CONGESTION = MappingProxyType({"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP})
DEFAULT_LEASE_MS = 1000
DEFAULT_KEEP_ALIVE = 4  # keep-alives per lease
HELLO_POLL_S = 0.1  # harness HEARTBEAT period until HELLO
BYE_LINGER_S = 1.0  # how long a stopping target waits for the harness to leave after its BYE
USRPWD_KEYS = ("user", "password", "dictionary_file")
CLOSE_TIMEOUT_S = 2.0  # how long closing a session may take (s) before it is left to finish alone
GONE_CLOSE_TIMEOUT_S = 0.5  # the same once the peer is gone: a frozen peer blocks close ~10 s
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


@dataclass
class ZenohStats:
    """Counters only this transport has (the shared ones are in ``LinkStats``)."""

    put_failures: int = 0
    duplicate_hellos: int = 0
    heartbeats_sent: int = 0
    close_failures: int = 0  # session closes that timed out or raised (see close_session)


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


def config_entries(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                   multicast_scouting: bool = False, gossip: bool = False,
                   tls: Mapping[str, object] | None = None, lease_ms: int = DEFAULT_LEASE_MS,
                   keep_alive: int = DEFAULT_KEEP_ALIVE, shared_memory: bool | None = None,
                   usrpwd: Mapping[str, str] | None = None) -> dict[str, object]:
    """The Zenoh config this transport uses, as ``{config path: JSON value}``.

    ``usrpwd``: Zenoh's user/password authentication (``USRPWD_KEYS``): ``user`` and
    ``password`` to present, ``dictionary_file`` (lines ``user:password``) to accept
    only those peers; or ``dictionary``, the lines themselves, which
    :func:`open_session` writes to a private file only while the session opens (a
    run's own credentials: ``hil.adapters.zenoh_options.run_usrpwd``, ``AUTH_ENV``).

    ``lease_ms`` (ms) is how long a peer may stay silent before this session's lease
    runs out at the other end; ``shared_memory`` None keeps Zenoh's default (on).

    Raises:
        ConfigError: a bad mode, endpoint, TLS key or lease (the message names it).
    """
    if mode not in MODES:
        raise ConfigError(f"zenoh mode={mode!r}: expected one of {', '.join(MODES)}")
    if not isinstance(lease_ms, int) or lease_ms < 100:
        raise ConfigError(f"zenoh lease_ms={lease_ms!r}: expected an integer number of ms >= 100")
    if not isinstance(keep_alive, int) or keep_alive < 1:
        raise ConfigError(f"zenoh keep_alive={keep_alive!r}: expected an integer >= 1")
    entries: dict[str, object] = {
        "mode": mode,
        "connect/endpoints": _check_endpoints("connect", connect),
        "listen/endpoints": _check_endpoints("listen", listen),
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
    if shared_memory is not None:
        entries["transport/shared_memory/enabled"] = bool(shared_memory)
    value: object  # a usrpwd value (str), then a tls value
    for key, value in (usrpwd or {}).items():
        if key == "dictionary":
            continue  # inline lines: open_session writes them (see above)
        if key not in USRPWD_KEYS:
            raise ConfigError(f"zenoh usrpwd key {key!r} is unknown; valid: {', '.join(USRPWD_KEYS)}")
        entries[f"transport/auth/usrpwd/{key}"] = str(value)
    for key, value in (tls or {}).items():
        if key not in TLS_KEYS:
            raise ConfigError(f"zenoh tls key {key!r} is unknown; valid: {', '.join(TLS_KEYS)}")
        entries[f"transport/link/tls/{key}"] = value
    return entries


def make_config(**options: object) -> zenoh.Config:
    """A ``zenoh.Config`` from ``config_entries(**options)``; nothing else is defaulted
    from the environment.

    Raises:
        ConfigError: as ``config_entries``, or Zenoh rejects a value.
    """
    cfg = zenoh.Config()
    for key, value in config_entries(**options).items():  # type: ignore[arg-type]
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


def _tcp_answers(endpoint: str, *, timeout_s: float = 0.5) -> bool:
    """True when something accepts a TCP connection at a ``tcp/`` or ``tls/`` endpoint
    (to tell "nothing listens" from "a session was refused"). Other protocols: False."""
    import socket

    proto, _, address = endpoint.partition("/")
    host, sep, port = address.split("?", 1)[0].split("#", 1)[0].rpartition(":")
    if proto not in ("tcp", "tls") or not sep or not port.isdigit():
        return False
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


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


def _is(data: bytes, mtype: MsgType) -> bool:
    return len(data) >= protocol.HEADER_SIZE and data[:4] == protocol.MAGIC and data[5] == mtype


class ZenohHalf:
    """The harness's Zenoh side of one vehicle, not itself a ``Link``: the session, the
    publisher on ``h2t``, the harness's liveliness token and a subscriber to the
    target's, and a bounded close. ``ZenohLink`` adds the ``t2h`` subscriber and the
    HELLO handshake; ``hil.adapters.mixed.MixedLink`` uses it as its frame path.

    Args:
        options as ``ZenohLink``; ``what`` names the link in messages.

    Raises:
        ConfigError: a bad option (checked here, before anything opens).
    """

    def __init__(self, *, vehicle_id: int, connect: Sequence[str], listen: Sequence[str], mode: str,
                 key_prefix: str, multicast_scouting: bool, tls: Mapping[str, object] | None,
                 usrpwd: Mapping[str, str] | None, congestion_control: str, lease_ms: int,
                 shared_memory: bool | None, what: str = "zenoh link") -> None:
        if congestion_control not in CONGESTION:
            raise ConfigError(f"zenoh congestion_control={congestion_control!r}: expected 'block' or 'drop'")
        if not connect and not listen:
            raise ConfigError(f"{what} needs at least one connect or listen endpoint")
        self.what = what
        self.keys = Keys.of(key_prefix, vehicle_id)
        self.congestion_control = congestion_control
        self.connect, self.listen = list(connect), list(listen)
        self.usrpwd = bool(usrpwd)
        self.dictionary = (usrpwd or {}).get("dictionary")  # the run's own credentials (zenoh_options.run_usrpwd)
        self.config = make_config(mode=mode, connect=connect, listen=listen, tls=tls, usrpwd=usrpwd,
                                  multicast_scouting=multicast_scouting, lease_ms=lease_ms,
                                  shared_memory=shared_memory)
        self.stats = ZenohStats()
        self._session: zenoh.Session | None = None
        self._publisher: zenoh.Publisher | None = None
        self._entities: list[object] = []

    def open(self, *, on_target_token: Callable[[zenoh.Sample], None],
             on_t2h: Callable[[zenoh.Sample], None] | None = None) -> None:
        """Open the session and declare: the publisher on ``h2t``, a subscriber on
        ``t2h`` (with ``on_t2h``), the harness's token, and a subscriber to the target's
        token (``on_target_token`` gets its PUT and DELETE, history included).

        Raises:
            TransportError: the session or a declaration failed.
        """
        self._session = s = open_session(self.config, f"connect={self.connect} listen={self.listen}",
                                         dictionary=self.dictionary)
        try:
            self._publisher = s.declare_publisher(self.keys.h2t, congestion_control=CONGESTION[self.congestion_control])
            # Zenoh undeclares an entity when its Python object is dropped: keep them all.
            if on_t2h is not None:
                self._entities.append(s.declare_subscriber(self.keys.t2h, on_t2h))
            self._entities += [
                s.liveliness().declare_token(self.keys.harness),
                s.liveliness().declare_subscriber(self.keys.alive, on_target_token, history=True),
            ]
        except zenoh.ZError as err:
            raise TransportError(f"zenoh declarations on {self.keys.h2t!r} failed: {err}") from err

    def put(self, data: bytes, link_stats: LinkStats) -> None:
        """Publish one message on ``h2t``.

        Raises:
            TransportError: not open, or the put failed (counted in ``stats.put_failures``).
        """
        pub = self._publisher
        if pub is None:
            raise TransportError(f"{self.what} is not open")
        try:
            pub.put(data)
        except zenoh.ZError as err:
            self.stats.put_failures += 1
            link_stats.last_error = f"zenoh put failed: {err}"
            raise TransportError(f"zenoh put on {self.keys.h2t!r} failed: {err}") from err

    def no_session_reason(self, timeout_s: float) -> str | None:
        """Why nothing came up, when no Zenoh peer or router is connected (None when one is)."""
        s = self._session
        if s is None or s.is_closed():
            return None
        info = s.info
        if info.peers_zid() or info.routers_zid():
            return None
        answering = [ep for ep in self.connect if _tcp_answers(ep)]
        if answering:
            tls = any(ep.startswith("tls/") for ep in answering)
            why = ("the TLS handshake was refused: check that root_ca_certificate signed the target's "
                   "certificate, the name in the endpoint matches it, and (mTLS) ours"
                   if tls else "user/password authentication was refused: check the user, the password "
                   "and the target's --auth-dictionary" if self.usrpwd
                   else "another program holds the port, or the target asks for TLS or a password")
            return f"{', '.join(answering)} answers, but no zenoh session came up within {timeout_s:g} s: {why}"
        return (f"no zenoh peer reached within {timeout_s:g} s (connect={self.connect}, "
                f"listen={self.listen}): is the target running, e.g. with "
                f"--transport zenoh --listen tcp/0.0.0.0:7447, and reachable?")

    def sender_note(self) -> str:
        """Who can have sent a BYE in this session, as a clause: Zenoh does not say
        which peer published a sample, so only the session's admission tells."""
        if self.dictionary is not None:
            return "sent by this run's target: only it and this harness hold the run's own credentials"
        if self.usrpwd:
            return "sent by a peer holding target.zenoh.auth's credentials (zenoh does not say which)"
        return ("its sender cannot be told: zenoh does not say which peer published it, and the session admits any "
                "peer that reaches the endpoint (target.zenoh.per_run_auth closes it)")

    def close(self, link_stats: LinkStats, *, peer_gone: bool = False) -> None:
        """Undeclare everything and close the session, bounded by ``CLOSE_TIMEOUT_S``
        (``GONE_CLOSE_TIMEOUT_S`` when the peer is already gone: a frozen peer made
        an unbounded close block ~10 s and then raise "close operation timed out",
        which cost a run its summary). Idempotent; never raises."""
        session, self._session = self._session, None
        self._publisher, self._entities = None, []
        if session is not None and not session.is_closed():
            reason = close_session(session, timeout_s=GONE_CLOSE_TIMEOUT_S if peer_gone else CLOSE_TIMEOUT_S)
            if reason is not None:
                self.stats.close_failures += 1
                link_stats.last_error = reason


class ZenohLink(Link):
    """Harness side over Zenoh: publishes on ``h2t``, receives on ``t2h`` (module docstring).

    Options are keyword-only; ``connect``/``listen`` are Zenoh endpoints
    (``tcp/host:port``, ``tls/host:port``); ``congestion_control`` is ``"block"``
    (default, nothing dropped silently) or ``"drop"``; ``lease_ms`` as in
    ``config_entries``. ``config`` is the ``zenoh.Config`` the session opens with;
    ``zenoh_stats`` counts what only this transport has.
    """

    transport_name = "zenoh"

    def __init__(self, *, vehicle_id: int, clock: Clock, connect: Sequence[str] = ("tcp/127.0.0.1:7447",),
                 listen: Sequence[str] = (), mode: str = "peer", key_prefix: str = "hil",
                 multicast_scouting: bool = False, tls: Mapping[str, object] | None = None,
                 usrpwd: Mapping[str, str] | None = None,
                 congestion_control: str = "block", lease_ms: int = DEFAULT_LEASE_MS,
                 shared_memory: bool | None = None, rx_queue_size: int = 1024,
                 rx_queue: queue.Queue[Received] | None = None) -> None:
        """Raises ConfigError: a bad option (checked here, before anything opens)."""
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        self._hb_thread: threading.Thread | None = None
        self._poke = threading.Event()  # wakes the HEARTBEAT loop (HELLO seen, token seen, closing)
        self._hello_seen = threading.Event()
        self._hello_lock = threading.Lock()
        self._target_seen = False
        self.zenoh = ZenohHalf(vehicle_id=vehicle_id, connect=connect, listen=listen, mode=mode,
                               key_prefix=key_prefix, multicast_scouting=multicast_scouting, tls=tls,
                               usrpwd=usrpwd, congestion_control=congestion_control, lease_ms=lease_ms,
                               shared_memory=shared_memory)
        self.zenoh_stats = self.zenoh.stats
        self.keys, self.config = self.zenoh.keys, self.zenoh.config

    def _open(self) -> None:
        self.zenoh.open(on_target_token=self._on_liveliness, on_t2h=self._on_sample)
        self._hb_thread = threading.Thread(target=self._ask_hello, name=f"zenoh-hello-{self.vehicle_id}",
                                           daemon=True)
        self._hb_thread.start()

    def _ask_hello(self) -> None:
        while not (self._hello_seen.is_set() or self._closed or not self.alive):
            try:
                self.zenoh.put(protocol.encode(Heartbeat(self.vehicle_id, self.clock.now_ns())), self.stats)
            except TransportError:
                return
            self.zenoh_stats.heartbeats_sent += 1
            self._poke.wait(HELLO_POLL_S)
            self._poke.clear()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        t_rx = self.clock.now_ns()
        data = sample.payload.to_bytes()
        if _is(data, MsgType.HELLO):
            with self._hello_lock:
                if self._hello_seen.is_set():
                    self.zenoh_stats.duplicate_hellos += 1
                    return
                self._hello_seen.set()
            self._poke.set()
        self._on_message_bytes(data, t_rx)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._target_seen = True
            self._poke.set()  # ask for HELLO now rather than at the next tick
        elif sample.kind == zenoh.SampleKind.DELETE:
            self._mark_gone(f"zenoh liveliness lost: token {self.keys.alive!r} went away "
                            f"(target process exited, closed its session or its lease expired)")

    def _send_bytes(self, data: bytes) -> None:
        self.zenoh.put(data, self.stats)

    def _mark_gone(self, reason: str) -> None:
        if reason.startswith("target said bye"):  # anyone in the session could have said it
            reason = f"{reason}; {self.zenoh.sender_note()}"
        elif not self.zenoh.usrpwd:  # the target may have left on a BYE the harness never sent
            reason = (f"{reason}; a BYE to the target from any peer on its endpoint ends it the same way, and "
                      f"its sender cannot be told (target.zenoh.per_run_auth admits only this run's peers)")
        super()._mark_gone(reason)

    def _no_hello_reason(self, timeout_s: float) -> str:
        if self.peer_gone_reason:
            return super()._no_hello_reason(timeout_s)
        reason = self.zenoh.no_session_reason(timeout_s)
        if reason is not None:
            return reason
        if not self._target_seen:
            return (f"zenoh is connected but no target serves {self.keys.alive!r} within {timeout_s:g} s: "
                    f"check the target's --vehicle and --key-prefix")
        return f"the target at {self.keys.alive!r} did not say hello within {timeout_s:g} s"

    def _close_transport(self) -> None:
        poke = getattr(self, "_poke", None)
        if poke is not None:
            poke.set()
        thread = getattr(self, "_hb_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        half = getattr(self, "zenoh", None)
        if half is not None:
            half.close(self.stats, peer_gone=not self.alive)


def serve_endpoint(ep: Endpoint, **options: object) -> None:
    """Target side: serve ``ep`` (``hil.adapters.zenoh_target.serve_endpoint``, where the
    options are documented; kept here for its importers, and reached through the
    table in :mod:`hil.adapters.transports` because ``zenoh_target`` imports this module).

    Raises:
        ConfigError: a bad option. TransportError: the session cannot be opened.
    """
    transports.serve_function(transports.Transport.ZENOH)(ep, **options)

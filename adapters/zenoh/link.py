"""The Zenoh transport: the target is a remote host (or a local process) on a Zenoh network.

Each Zenoh sample carries exactly one encoded protocol message (PROTOCOL.md). A run
uses four key expressions per vehicle, under a key prefix (``key_prefix``, default
``hil``) that both sides are given::

    {prefix}/v{vehicle_id}/h2t      harness -> target: FRAME, SYNC_REQUEST, HEARTBEAT, ERROR, BYE, COMMAND
    {prefix}/v{vehicle_id}/t2h      target -> harness: HELLO, ESTIMATE, SYNC_RESPONSE, HEARTBEAT, ERROR, BYE,
                                    COMMAND (replies)
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
target's session closed, its process died, or its link's lease expired) after its
HELLO marks the link gone. A DELETE before the HELLO does not: a target serving run
after run undeclares the token of the run it is finishing before it declares the
next one's, and a harness that subscribed in between sees that DELETE first (CI saw
it: the link was marked gone by the previous run's token); the harness keeps asking
and the hello timeout says so if no target comes back. A killed process closes its
TCP socket and is noticed in a few ms (3-4 ms measured on loopback). A silent peer
(frozen process, pulled cable) is noticed when the lease it announced expires:
``transport/link/tx/lease`` is set to ``lease_ms`` (default 1000 ms, Zenoh's own
default is 10 s) with a keep-alive every ``lease_ms / keep_alive`` (250 ms), on both
sides; a frozen (SIGSTOP) target was noticed after 0.9 s. It is the silent side's announced lease that counts, so a target
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

import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import MappingProxyType

from hil.adapters.link import Link, LinkStats, Received
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Heartbeat, MsgType
from hil.adapters.zenoh.options import ZenohOptions
from hil.adapters.zenoh.session import CLOSE_TIMEOUT_S, Keys, _is, close_session, make_config, open_session
from hil.common.errors import ConfigError, TransportError
from hil.timing.clock import Clock

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the zenoh transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err

CONGESTION = MappingProxyType({"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP})
HELLO_POLL_S = 0.1  # harness HEARTBEAT period until HELLO
GONE_CLOSE_TIMEOUT_S = 0.5  # the same as CLOSE_TIMEOUT_S once the peer is gone: a frozen peer blocks close ~10 s


@dataclass
class ZenohStats:
    """Counters only this transport has (the shared ones are in ``LinkStats``)."""

    put_failures: int = 0
    duplicate_hellos: int = 0
    heartbeats_sent: int = 0
    close_failures: int = 0  # session closes that timed out or raised (see close_session)


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


class ZenohHalf:
    """The harness's Zenoh side of one vehicle, not itself a ``Link``: the session, the
    publisher on ``h2t``, the harness's liveliness token and a subscriber to the
    target's, and a bounded close. ``ZenohLink`` adds the ``t2h`` subscriber and the
    HELLO handshake; ``hil.adapters.mixed.link.MixedLink`` uses it as its frame path.

    Args:
        options: the session's (``ZenohOptions``); ``what`` names the link in messages.

    Raises:
        ConfigError: a bad option (checked here, before anything opens).
    """

    def __init__(self, *, vehicle_id: int, options: ZenohOptions, what: str = "zenoh link") -> None:
        if options.congestion_control not in CONGESTION:
            raise ConfigError(f"zenoh congestion_control={options.congestion_control!r}: expected 'block' or 'drop'")
        if not options.connect and not options.listen:
            raise ConfigError(f"{what} needs at least one connect or listen endpoint")
        self.what = what
        self.options = options
        self.keys = Keys.of(options.key_prefix, vehicle_id)
        self.congestion_control = options.congestion_control
        self.connect, self.listen = list(options.connect), list(options.listen)
        self.usrpwd = bool(options.usrpwd)
        self.dictionary = (options.usrpwd or {}).get("dictionary")  # the run's own credentials (ZenohOptions.for_run)
        self.config = make_config(options)
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

    ``options`` (``ZenohOptions``): at least one ``connect`` or ``listen`` endpoint
    (``tcp/host:port``, ``tls/host:port``); ``congestion_control`` ``"block"`` (the
    default, nothing dropped silently) or ``"drop"``; ``lease_ms`` as in
    ``hil.adapters.zenoh.session.config_entries``. ``config`` is the ``zenoh.Config``
    the session opens with; ``zenoh_stats`` counts what only this transport has.
    """

    transport_name = "zenoh"

    def __init__(self, *, vehicle_id: int, clock: Clock, options: ZenohOptions | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None) -> None:
        """Raises ConfigError: a bad option (checked here, before anything opens)."""
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        self._hb_thread: threading.Thread | None = None
        self._poke = threading.Event()  # wakes the HEARTBEAT loop (HELLO seen, token seen, closing)
        self._hello_seen = threading.Event()
        self._hello_lock = threading.Lock()
        self._target_seen = False
        self._tokens_gone_before_hello = 0  # DELETEs of the target's token before its HELLO
        self.options = options or ZenohOptions()
        self.zenoh = ZenohHalf(vehicle_id=vehicle_id, options=self.options)
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
            with self._hello_lock:  # against a HELLO coming in on another of Zenoh's threads
                if not self._hello_seen.is_set():
                    # Not the target this link talks to yet: a target serving run after run
                    # undeclares the token of the run it is finishing before it declares the
                    # next run's, and this link's history can hold the old one. Keep asking;
                    # a target that left for good ends in the hello timeout, which says so.
                    self._target_seen = False
                    self._tokens_gone_before_hello += 1
                    return
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
        if not self._target_seen and self._tokens_gone_before_hello:
            return (f"the target's token {self.keys.alive!r} went away before its HELLO and no target serves it "
                    f"now ({timeout_s:g} s): the target exited or closed its session while this harness waited")
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


__all__ = ["CONGESTION", "ZenohHalf", "ZenohLink", "ZenohStats"]

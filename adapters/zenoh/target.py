"""Target side of the Zenoh transport: serve an ``Endpoint`` to one harness, or to
harness after harness (a target on a bench device), until stopped.

The keys, handshake and liveness are those of ``hil.adapters.zenoh.link`` (its
module docstring). Serving starts with one line on stderr that says where the
target listens or connects, its keys, clock and capabilities, so that a person who
started it by hand (``hil target cv --transport zenoh --listen tcp/0.0.0.0:7447``)
knows what a harness must be told.

With ``keep_serving`` the Zenoh session stays open between runs: each harness gets
a fresh endpoint (same AI, clock and command handler; the AI object keeps its
state, e.g. a model swapped by command), with its own HELLO and liveliness token;
SIGTERM or Ctrl-C ends it (saying BYE to a harness that is connected).
"""

from __future__ import annotations

import itertools
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

from hil.adapters.sdk import announce_line, fresh_endpoint, said_bye, serving, session_line, stop_on_sigterm
from hil.adapters.wire.messages import MsgType
from hil.adapters.zenoh.options import ZenohOptions
from hil.adapters.zenoh.session import BYE_LINGER_S, CLOSE_TIMEOUT_S, Keys, _is, close_session, open_with
from hil.common.errors import ConfigError, TransportError

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint

__all__ = ["serve_endpoint", "startup_line", "where"]


def where(options: ZenohOptions) -> str:
    """Where a target's session listens and connects, as a clause for its lines."""
    return " and ".join(part for part in (f"listening on {', '.join(options.listen)}" if options.listen else "",
                                          f"connecting to {', '.join(options.connect)}" if options.connect else "")
                        if part)


def startup_line(ep: Endpoint, *, options: ZenohOptions, keys: Keys, keep_serving: bool) -> str:
    """What a person starting the target by hand needs to know, in one line."""
    return announce_line(ep, transport="zenoh", where=where(options), keys=f"{keys.h2t.rsplit('/', 1)[0]}/*",
                         access=_security(options), keep_serving=keep_serving)


def _security(options: ZenohOptions) -> str:
    parts = []
    if any(str(e).startswith(("tls/", "quic/")) for e in (*options.listen, *options.connect)):
        parts.append("mutual TLS" if (options.tls or {}).get("enable_mtls") else "TLS")
    if (options.usrpwd or {}).get("dictionary"):
        parts.append("user/password of this run (from the harness that started it)")
    elif (options.usrpwd or {}).get("dictionary_file"):
        parts.append("user/password")
    return " + ".join(parts) or "open (anyone who reaches the endpoint can join; see README, threat model)"


def serve_endpoint(ep: Endpoint, *, options: ZenohOptions | None = None, vehicle_id: int = 0,
                   keep_serving: bool = False, announce: Callable[[str], None] | None = None) -> None:
    """Serve ``ep`` on vehicle ``vehicle_id`` until the harness says BYE or its
    liveliness token goes away (with ``keep_serving``: then wait for the next
    harness), or SIGTERM/Ctrl-C (then the target says BYE). ``options``
    (``ZenohOptions``): listens on ``listen`` (how a harness reaches a device, e.g.
    ``tcp/0.0.0.0:7447``) and/or connects to ``connect``; a ``usrpwd``
    ``dictionary_file`` admits only the peers it lists. ``announce`` gets the startup
    line and one line per session as it ends (default: stderr).

    Raises:
        ConfigError: a bad option, or neither ``listen`` nor ``connect`` given.
        TransportError: the session cannot be opened (e.g. the port is taken).
    """
    o = options or ZenohOptions()
    if not o.listen and not o.connect:
        raise ConfigError("a zenoh target needs --listen ENDPOINT (e.g. tcp/0.0.0.0:7447) or --connect ENDPOINT")
    keys = Keys.of(o.key_prefix, vehicle_id)
    session = open_with(o)
    quit_ = threading.Event()  # SIGTERM or Ctrl-C: no further runs
    current = ep

    def on_term() -> None:  # between two harnesses (within one, serving's handler has it)
        quit_.set()
        current.stop()

    say = announce or (lambda text: print(text, file=sys.stderr, flush=True))
    try:
        with stop_on_sigterm(on_term):
            say(startup_line(ep, options=o, keys=keys, keep_serving=keep_serving))
            for n in itertools.count(1):
                ended = _serve_one(session, current, keys=keys, vehicle_id=vehicle_id, quit_=quit_)
                if ended is not None:
                    say(session_line(current, n, f"the harness on {keys.h2t}", ended))
                if quit_.is_set() or not keep_serving:
                    return
                current = fresh_endpoint(ep, current)
    finally:
        close_session(session, timeout_s=CLOSE_TIMEOUT_S)  # bounded: the harness may be frozen


TOKEN_GRACE_S = 0.2  # after the harness's token went away, how long its BYE may still come


def _serve_one(session: zenoh.Session, ep: Endpoint, *, keys: Keys, vehicle_id: int,
               quit_: threading.Event) -> str | None:
    """One harness: declarations, HELLO, serve until it leaves or we are stopped.
    Returns how the session ended (None: it never began)."""
    if quit_.is_set():  # a SIGTERM while ``ep`` was being made stopped the endpoint before it
        return None
    engaged = threading.Event()  # a FRAME or SYNC_REQUEST came: the handshake is over
    harness_gone = threading.Event()  # BYE from the harness, or its token went away

    def on_sample(sample: zenoh.Sample) -> None:
        t_rx = ep.clock.now_ns()
        data = sample.payload.to_bytes()
        try:
            if _is(data, MsgType.HEARTBEAT):
                if not engaged.is_set():
                    ep.send(ep.hello())
                return
            engaged.set()
            if _is(data, MsgType.BYE):
                harness_gone.set()
            ep.on_message_bytes(data, t_rx)
        except TransportError:
            pass  # the session is closing: nothing can be answered any more

    token_gone = threading.Event()  # the harness's liveliness token went away

    def on_harness(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            token_gone.set()
            harness_gone.set()
            # A leaving harness's token DELETE can overtake its BYE (declarations travel
            # at a higher priority): the BYE, coming just after, ends the session as
            # said (and its line says so); a harness that vanished, the grace's end.
            grace = threading.Timer(TOKEN_GRACE_S, ep.stop)
            grace.daemon = True
            grace.start()

    entities: list[object] = []
    # The publisher is written from several threads (the inference worker, Zenoh's
    # callbacks answering a HEARTBEAT); undeclaring it while a put is under way fails
    # in the binding ("Already borrowed"), so puts and the undeclaring take turns here,
    # and a put once undeclaring has begun is refused as the session closing.
    pub_turn = threading.Lock()
    undeclaring = threading.Event()
    try:
        pub = session.declare_publisher(keys.t2h, congestion_control=zenoh.CongestionControl.BLOCK)

        def send(data: bytes) -> None:
            with pub_turn:
                if undeclaring.is_set():
                    raise TransportError(f"zenoh put on {keys.t2h!r}: the session is closing")
                try:
                    pub.put(data)
                except zenoh.ZError as err:
                    raise TransportError(f"zenoh put on {keys.t2h!r} failed: {err}") from err

        # Declarations before HELLO: a harness that has our HELLO knows our subscriber,
        # or its first frame would find no match and vanish. Zenoh undeclares an entity
        # when its Python object is dropped: keep them all.
        entities += [pub, session.declare_subscriber(keys.h2t, on_sample),
                     session.liveliness().declare_subscriber(keys.harness, on_harness)]
        # SIGTERM stops this session and any further; leaving says BYE unless the
        # harness left first, and lingers: our token's DELETE can overtake the BYE
        # (declarations travel at a higher priority).
        with serving(ep, vehicle_id=vehicle_id, harness_gone=harness_gone, linger_s=BYE_LINGER_S,
                     on_term=quit_.set):
            ep.start(send)  # a HEARTBEAT that comes before this is answered by the next one
            entities.append(session.liveliness().declare_token(keys.alive))
            try:
                # No timeout: a waking main thread would take the GIL from a spinning AI.
                # A POSIX lock wait still lets SIGTERM and Ctrl-C through.
                ep.wait_stopped()
            except KeyboardInterrupt:
                quit_.set()
                ep.stop()
    except zenoh.ZError as err:
        raise TransportError(f"zenoh declarations on {keys.h2t!r} failed: {err}") from err
    finally:  # serving joined the endpoint's worker
        with pub_turn:
            undeclaring.set()
        for entity in reversed(entities):
            undeclare = getattr(entity, "undeclare", None)
            if undeclare is not None:
                try:
                    undeclare()  # the next harness must see this run's token go and a new one come
                except (zenoh.ZError, RuntimeError):  # RuntimeError: in use elsewhere; dropped with the list
                    pass
        entities.clear()
    return (said_bye(ep) or ("stopped (SIGTERM)" if quit_.is_set() else "")
            or ("the harness went away (its liveliness token)" if token_gone.is_set() else "the session ended"))

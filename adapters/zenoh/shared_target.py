"""A shared target over Zenoh: one session subscribed to every served vehicle's keys.

Each vehicle keeps the keys, handshake and liveness of ``hil.adapters.zenoh.link``
(``{prefix}/{vehicle}/h2t`` and so on): a harness reaches vehicle ``v`` of the
shared target as it would reach a target of its own, at the one endpoint the shared
target listens on. Each vehicle is served by ``hil.adapters.zenoh.target``'s
one-harness loop on its own thread with a ``BatchedEndpoint``; all of them feed one
``BatchScheduler``. It serves one run per vehicle (or, with ``keep_serving``, run
after run) until SIGTERM/Ctrl-C.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Mapping, Sequence

from hil.adapters.batching import BatchedEndpoint, BatchScheduler
from hil.adapters.sdk import stop_on_sigterm
from hil.adapters.zenoh.options import DEFAULT_LEASE_MS
from hil.adapters.zenoh.session import CLOSE_TIMEOUT_S, Keys, close_session, make_config, open_session
from hil.adapters.zenoh.target import _serve_one, _security, startup_line
from hil.common.errors import ConfigError


def serve_shared(scheduler: BatchScheduler, make_endpoint: Callable[[], BatchedEndpoint], *,
                 vehicles: Sequence[int], listen: Sequence[str] = (), connect: Sequence[str] = (),
                 mode: str = "peer", key_prefix: str = "hil", multicast_scouting: bool = False,
                 tls: Mapping[str, object] | None = None, lease_ms: int = DEFAULT_LEASE_MS,
                 keep_serving: bool = False, usrpwd: Mapping[str, str] | None = None) -> None:
    """Serve ``vehicles`` (ids) from one Zenoh session until each vehicle's harness
    has left (``keep_serving``: until SIGTERM/Ctrl-C).

    Raises:
        ConfigError: no vehicles, or neither ``listen`` nor ``connect``.
        TransportError: the session cannot be opened.
    """
    if not vehicles:
        raise ConfigError("a shared zenoh target needs --vehicles (e.g. --vehicles 4, or 0,2,3)")
    if not listen and not connect:
        raise ConfigError("a zenoh target needs --listen ENDPOINT (e.g. tcp/0.0.0.0:7447) or --connect ENDPOINT")
    cfg = make_config(mode=mode, connect=connect, listen=listen, tls=tls, multicast_scouting=multicast_scouting,
                      lease_ms=lease_ms, usrpwd=usrpwd)
    session = open_session(cfg, f"listen={list(listen)} connect={list(connect)}",
                           dictionary=(usrpwd or {}).get("dictionary"))
    quit_ = threading.Event()
    current: dict[int, BatchedEndpoint] = {}
    lock = threading.Lock()

    def on_term(*_: object) -> None:
        quit_.set()
        with lock:
            for ep in current.values():
                ep.stop()

    def serve_vehicle(vid: int) -> None:
        keys = Keys.of(key_prefix, vid)
        while not quit_.is_set():
            ep = make_endpoint()
            with lock:
                current[vid] = ep
            _serve_one(session, ep, keys=keys, vehicle_id=vid, quit_=quit_)
            if not keep_serving:
                return

    scheduler.start()
    try:
        with stop_on_sigterm(on_term):
            first = make_endpoint()
            line = startup_line(first, listen=listen, connect=connect, keys=Keys.of(key_prefix, vehicles[0]),
                                keep_serving=keep_serving, security=_security(listen, connect, tls, usrpwd))
            print(f"{line}; shared by vehicles {', '.join(map(str, vehicles))} "
                  f"(window {scheduler.window_ns / 1e6:g} ms, batches of at most {scheduler.max_batch})",
                  file=sys.stderr, flush=True)
            threads = [threading.Thread(target=serve_vehicle, args=(v,), name=f"vehicle-{v}", daemon=True)
                       for v in vehicles]
            for t in threads:
                t.start()
            try:
                for t in threads:
                    while t.is_alive():
                        t.join(timeout=0.5)  # a timed join lets Ctrl-C through
            except KeyboardInterrupt:
                on_term()
                for t in threads:
                    t.join(timeout=5.0)
    finally:
        scheduler.stop()
        close_session(session, timeout_s=CLOSE_TIMEOUT_S)


__all__ = ["serve_shared"]

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
from collections.abc import Callable, Sequence

from hil.adapters.batching import BatchedEndpoint, BatchScheduler
from hil.adapters.sdk import stop_on_sigterm
from hil.adapters.zenoh.options import ZenohOptions
from hil.adapters.zenoh.session import CLOSE_TIMEOUT_S, Keys, close_session, open_with
from hil.adapters.zenoh.target import _serve_one, startup_line
from hil.common.errors import ConfigError


def serve_shared(scheduler: BatchScheduler, make_endpoint: Callable[[], BatchedEndpoint], *,
                 vehicles: Sequence[int], options: ZenohOptions | None = None, keep_serving: bool = False) -> None:
    """Serve ``vehicles`` (ids) from one Zenoh session (``options``, as a target of
    its own takes them) until each vehicle's harness has left (``keep_serving``:
    until SIGTERM/Ctrl-C).

    Raises:
        ConfigError: no vehicles, or neither ``listen`` nor ``connect``.
        TransportError: the session cannot be opened.
    """
    if not vehicles:
        raise ConfigError("a shared zenoh target needs --vehicles (e.g. --vehicles 4, or 0,2,3)")
    o = options or ZenohOptions()
    if not o.listen and not o.connect:
        raise ConfigError("a zenoh target needs --listen ENDPOINT (e.g. tcp/0.0.0.0:7447) or --connect ENDPOINT")
    session = open_with(o)
    quit_ = threading.Event()
    current: dict[int, BatchedEndpoint] = {}
    lock = threading.Lock()

    def on_term(*_: object) -> None:
        quit_.set()
        with lock:
            for ep in current.values():
                ep.stop()

    def serve_vehicle(vid: int) -> None:
        keys = Keys.of(o.key_prefix, vid)
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
            line = startup_line(first, options=o, keys=Keys.of(o.key_prefix, vehicles[0]), keep_serving=keep_serving)
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

"""Placement of a shared target (``target.shared: true``): one target process serves
every vehicle of the run, which batches their frames (``hil.adapters.batching``).

* ``transport: local``: the first vehicle's link starts the program once
  (``hil.adapters.local.shared_link.SharedLocalTarget``); every vehicle's link hands it its
  own socket (and frame ring) over a control socket, so each vehicle keeps its own
  session with PROTOCOL.md's framing.
* ``transport: zenoh``: every vehicle's link joins the same endpoints (``{port}``
  is ``zenoh.base_port``, vehicle 0's, for all) under its own keys; a ``command``,
  if given, is started once (with ``{vehicle_id}`` = 0) and must serve all the run's
  vehicles, e.g. ``hil.targets.cnn --shared --vehicles 4``; with no ``command`` the
  shared target runs elsewhere (another host: the paper's distributed placement).

The target's log is ``target-shared.log`` in the run folder; it writes every
frame's batch (batch number and size, vehicle, frame, its three stamps) to
``target-shared-batches.csv`` there (``HIL_BATCH_LOG``).
"""

from __future__ import annotations

import os
import queue
import subprocess
import threading
from pathlib import Path

from hil.adapters.batching import ENV_BATCH_LOG
from hil.adapters.link import Link, Received, open_link
from hil.adapters.local.shared_link import SharedLocalLink, SharedLocalTarget
from hil.adapters.process import die_with_parent
from hil.common.errors import TargetError
from hil.harness.config.model import RunConfig, Transport
from hil.harness.run.link_options import impair, target_command, zenoh_options
from hil.timing.clock import Clock

LOG_NAME = "target-shared.log"
BATCH_LOG_NAME = "target-shared-batches.csv"

_hosts: dict[str, SharedLocalTarget] = {}  # run folder -> its shared target process
_hosts_lock = threading.Lock()

__all__ = ["BATCH_LOG_NAME", "LOG_NAME", "shared_link"]


class _SharedNetworkProcess(SharedLocalTarget):
    """A shared Zenoh target started on this host: the program alone, no control socket."""

    def __init__(self, command: list[str], *, log_path: Path, env: dict[str, str]) -> None:
        self.command, self.log_path = command, log_path
        self._lock = threading.Lock()
        self._ctl = None
        self._log = open(log_path, "ab")  # noqa: SIM115 (closed in close())
        try:
            self.proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log,
                                         env=dict(os.environ, PYTHONUNBUFFERED="1", **env), start_new_session=True,
                                         preexec_fn=die_with_parent)
        except OSError as err:
            self._log.close()
            raise TargetError(f"target command {command[0]!r} cannot be started: {err.strerror or err} "
                              "(check target.command)") from err


def _host(cfg: RunConfig, *, vehicle_id: int, out_dir: Path) -> tuple[SharedLocalTarget | None, bool]:
    """The run's shared target process (started by vehicle 0's call), and whether this
    call started it (the caller then owns closing it). None: zenoh without a command.

    Raises:
        TargetError: it cannot be started, or a later vehicle finds none.
    """
    key = str(out_dir.resolve())
    if cfg.target.transport == Transport.ZENOH and not cfg.target.command:
        return None, False
    with _hosts_lock:
        if vehicle_id == 0 or key not in _hosts:
            if vehicle_id != 0:
                raise TargetError("shared target: vehicle 0's link starts the target process; it is not running")
            env = {ENV_BATCH_LOG: str(out_dir / BATCH_LOG_NAME)}
            cmd = target_command(cfg, vehicle_id=0)
            host = (SharedLocalTarget(cmd, log_path=out_dir / LOG_NAME, env=env)
                    if cfg.target.transport == Transport.LOCAL
                    else _SharedNetworkProcess(cmd, log_path=out_dir / LOG_NAME, env=env))
            _hosts[key] = host
            return host, True
        return _hosts[key], False


class _Owned:
    """The host as the run closes it: closing also forgets it for the run folder."""

    def __init__(self, host: SharedLocalTarget, key: str) -> None:
        self.host, self._key = host, key

    @property
    def pid(self) -> int | None:
        return self.host.pid

    def close(self) -> None:
        with _hosts_lock:
            if _hosts.get(self._key) is self.host:
                del _hosts[self._key]
        self.host.close()


def shared_link(cfg: RunConfig, *, vehicle_id: int, clock: Clock, out_dir: Path,
                rx: queue.Queue[Received] | None = None) -> tuple[Link, _Owned | None]:
    """Build (not open) vehicle ``vehicle_id``'s link to the run's shared target,
    starting that target on vehicle 0's call. Returns the link and, on vehicle 0's
    call, the process to close after every link (``close()``), else None.

    Raises:
        TargetError: the command cannot be started.
        TransportError / ConfigError: the transport options are unusable.
    """
    host, owner = _host(cfg, vehicle_id=vehicle_id, out_dir=out_dir)
    owned = _Owned(host, str(out_dir.resolve())) if (owner and host is not None) else None
    try:
        if cfg.target.transport == Transport.LOCAL:
            assert host is not None
            link: Link = SharedLocalLink(host=host, vehicle_id=vehicle_id, clock=clock, rx_queue=rx)
        else:  # zenoh: one set of endpoints (vehicle 0's), each vehicle its own keys
            link = open_link(Transport.ZENOH, vehicle_id=vehicle_id, clock=clock, rx_queue=rx,
                             options=zenoh_options(cfg, vehicle_id=0))
        impair(cfg, link, vehicle_id=vehicle_id, clock=clock)  # target.impair applies per vehicle as usual
    except BaseException:
        if owned is not None:
            owned.close()
        raise
    return link, owned

"""Where a campaign's episodes run: a local process pool, or a Dask cluster.

Both engines give ``run_campaign`` (campaign.py) a ``concurrent.futures`` executor
and take the same draws in the same order, so a campaign seed gives the same
episodes and corner cases on either (an episode depends only on its draw).

* ``ProcessEngine``: a ``spawn`` ``ProcessPoolExecutor`` on this machine; each episode
  writes straight into the campaign folder.
* ``DaskEngine``: a Dask ``distributed`` cluster, each episode a task whose result
  comes back as a ``concurrent.futures`` future into the pool's loop unchanged. Dask
  over Ray: pure-Python wheels that install here, a ``LocalCluster`` of worker
  processes that runs on two cores, and futures that plug into that loop (a stopped
  campaign can tell a running episode, left to finish, from a queued one, dropped). ``--scheduler ADDRESS`` connects to a running
  cluster (``dask scheduler`` / ``dask worker`` on other hosts); without it a
  ``LocalCluster`` of ``workers`` processes (one thread each, bound to 127.0.0.1) is
  started and closed with the campaign. A worker may be on another host with no
  shared disk: it runs the episode in a folder of its own and ships the episode
  folder back as a tar archive, which this process unpacks into that episode's
  folder and nowhere else (``unpack_episode``: regular files and folders only, no
  ``..``, no links).

Dask moves tasks and results with pickle, so whoever can talk to a scheduler runs
code in the campaign's workers (and, through results, in this process). The local
cluster is therefore closed to every other process: mutual TLS with a certificate
made for the campaign (``distributed.security.Security.temporary()``, kept in
memory; a client without it is refused), and no dashboard: the scheduler's HTTP
server, which Dask always starts (on 8787 by default), serves no routes on a free
loopback port, and the workers' likewise. A ``--scheduler`` cluster is as safe as
its network: use ``tls://`` with Dask's TLS settings (``distributed.comm.tls``),
which the client reads from Dask's configuration.
"""

from __future__ import annotations

import enum
import io
import json
import multiprocessing
import os
import shutil
import tarfile
import tempfile
import time
import uuid
from concurrent.futures import Future, InvalidStateError, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.search.episode import EpisodeResult, episode_dirname, init_worker, run_episode
from hil.harness.search.sampling import Draw
from hil.harness.search.spec import Campaign


class EngineKind(enum.Enum):
    """``hil search --engine``."""

    PROCESS = "process"
    DASK = "dask"


class ProcessEngine:
    """Episodes in a ``spawn`` process pool of ``workers`` processes on this machine."""

    kind = EngineKind.PROCESS

    def __init__(self, *, workers: int, gl_backend: str) -> None:
        self.workers = workers
        self.gl_backend = gl_backend
        self._ex: ProcessPoolExecutor | None = None

    def submit(self, c: Campaign, d: Draw, *, out: Path, shard: str) -> Future[EpisodeResult]:
        if self._ex is None:
            os.environ["MUJOCO_GL"] = self.gl_backend  # inherited by the spawned workers too
            self._ex = ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                           initializer=init_worker, initargs=(self.gl_backend,))
        return self._ex.submit(run_episode, c, d, campaign_dir=out, shard=shard, gl_backend=self.gl_backend)

    def reset(self) -> None:
        """Drop a broken pool (a worker was killed); the next submit starts a new one."""
        self.close()

    def close(self) -> None:
        if self._ex is not None:
            self._ex.shutdown(wait=True, cancel_futures=True)
            self._ex = None

    def describe(self) -> str:
        return f"process pool, {self.workers} workers"


def shipped_episode(c: Campaign, d: Draw, *, shard: str, gl_backend: str) -> tuple[str, bytes, int]:
    """A Dask task: run one episode in a scratch folder of this worker.

    Returns (the EpisodeResult as JSON, the episode folder as an uncompressed tar
    archive, ns spent packing it). Never raises for a failed episode (its status
    says ``error``)."""
    os.environ.setdefault("MUJOCO_GL", gl_backend)
    with tempfile.TemporaryDirectory(prefix="hil-episode-") as tmp:
        # A Dask task runs on a worker thread: signal handlers are the main thread's.
        r = run_episode(c, d, campaign_dir=Path(tmp), shard=shard, gl_backend=gl_backend,
                        install_signal_handlers=False)
        t0 = time.perf_counter_ns()
        buf = io.BytesIO()
        folder = Path(tmp) / "episodes" / episode_dirname(d.index)
        with tarfile.open(fileobj=buf, mode="w") as tar:
            if folder.is_dir():
                tar.add(folder, arcname=episode_dirname(d.index))
        return json.dumps(r.as_dict()), buf.getvalue(), time.perf_counter_ns() - t0


# Dask starts an HTTP server on every scheduler, worker and nanny whatever the
# dashboard setting: with these, they answer nothing (404) about the campaign.
_NO_HTTP_ROUTES: dict[str, list[str]] = {f"distributed.{role}.http.routes": []
                                          for role in ("scheduler", "worker", "nanny")}


def _campaign_security() -> Any:
    """Mutual TLS for a local cluster: a self-signed key and certificate made now, in
    memory, for this campaign only (every process of the cluster gets them from
    here; a client without them is refused).

    Raises:
        ConfigError: ``cryptography`` (which makes the certificate) is not installed.
    """
    from distributed.security import Security

    try:
        return Security.temporary()
    except ImportError as err:
        raise ConfigError("--engine dask: the local cluster's TLS certificate needs the 'cryptography' package; "
                          "pip install cryptography (or pip install \".[cluster]\")") from err


def _is_daemon() -> bool:
    """On a worker: whether its process is daemonic (and so may not have children)."""
    return bool(multiprocessing.current_process().daemon)


def _executing_keys(dask_worker: Any) -> list[str]:
    """On a worker (``Client.run``): the keys of the tasks it is running now."""
    return [str(ts.key) for ts in dask_worker.state.executing]


class _Shipped(Future[EpisodeResult]):
    """An episode's result once unpacked here. Cancelling it cancels its Dask task
    unless a worker is running it already: as in the process pool, a stopped
    campaign lets running episodes finish and drops only those not started."""

    def __init__(self, engine: DaskEngine, task: Any) -> None:
        super().__init__()
        self.engine = engine
        self.task = task

    def cancel(self) -> bool:
        if self.done():
            return False
        if str(self.task.key) in self.engine.executing():
            return False
        # This future first: the task's callback (``unpack``, on Dask's callback thread)
        # often runs before ``task.cancel()`` returns, and must find it cancelled, not
        # set the task's CancelledError as the episode's error.
        if not super().cancel():
            return False
        self.task.cancel()
        return True


class DaskEngine:
    """Episodes as tasks on a Dask cluster (see the module docstring).

    ``overhead_ns`` adds up, per episode, what the engine costs on the way back:
    packing the folder on the worker and transferring and unpacking it here.

    Raises (constructor):
        ConfigError: ``distributed`` is not installed, the scheduler cannot be
            reached within ``timeout_s``, or its workers are daemonic processes.
    """

    kind = EngineKind.DASK

    def __init__(self, *, gl_backend: str, scheduler: str | None = None, workers: int = 1,
                 timeout_s: float = 20.0) -> None:
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError as err:
            raise ConfigError(f"--engine dask: the Dask 'distributed' package is not installed ({err}); "
                              "pip install distributed") from err
        self.gl_backend = gl_backend
        self.scheduler = scheduler
        self._cluster: Any = None
        self.overhead_ns: list[int] = []
        t0 = time.perf_counter()
        try:
            if scheduler is None:
                os.environ["MUJOCO_GL"] = gl_backend  # the worker processes inherit it
                security = _campaign_security()
                # Workers start the simulator's own processes: they must not be daemonic.
                with dask.config.set({"distributed.worker.daemon": False, **_NO_HTTP_ROUTES}):
                    self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                 host="127.0.0.1", dashboard_address=None,
                                                 # Episode errors come back as results; a worker's
                                                 # heartbeat that meets the closing scheduler logged
                                                 # a traceback at ERROR (a clean run's stderr).
                                                 silence_logs=50,
                                                 security=security, protocol="tls://",
                                                 scheduler_kwargs={"dashboard": False,
                                                                   "dashboard_address": "127.0.0.1:0"})
                self.client = Client(self._cluster, security=security, timeout=timeout_s)
            else:
                self.client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError, RuntimeError) as err:
            self.close()
            if scheduler is None:
                raise ConfigError(f"--engine dask: the local Dask cluster did not start ({err})") from err
            raise ConfigError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({err})") from err
        daemonic = sorted(w for w, d in self.client.run(_is_daemon).items() if d)
        if daemonic:
            self.close()
            raise ConfigError(f"--scheduler {scheduler}: Dask workers {', '.join(daemonic[:3])} are daemonic processes, "
                              "which cannot start an episode's processes; start them with "
                              "DASK_DISTRIBUTED__WORKER__DAEMON=False")
        self.start_s = time.perf_counter() - t0
        threads = sum(self.client.nthreads().values())
        self.workers = max(1, threads)

    def submit(self, c: Campaign, d: Draw, *, out: Path, shard: str) -> Future[EpisodeResult]:
        task = self.client.submit(shipped_episode, c, d, shard=shard, gl_backend=self.gl_backend, pure=False,
                                  key=f"hil-episode-{c.campaign_id}-{d.index}-{uuid.uuid4().hex[:8]}")
        done = _Shipped(self, task)

        def unpack(f: Any) -> None:  # on a thread of the client's
            if done.cancelled():  # the campaign was stopped before this episode started
                return
            try:
                text, archive, pack_ns = f.result()
                t0 = time.perf_counter_ns()
                unpack_episode(archive, out / "episodes", name=episode_dirname(d.index))
                self.overhead_ns.append(pack_ns + time.perf_counter_ns() - t0)
                result: EpisodeResult | BaseException = EpisodeResult(**json.loads(text))
                if isinstance(result, EpisodeResult) and (result.index, result.dir) != (
                        d.index, f"episodes/{episode_dirname(d.index)}"):  # it names only its own folder
                    result = ValueError(f"episode {d.index}'s result names episode {result.index} "
                                        f"in {result.dir!r}")
            except BaseException as e:  # noqa: BLE001 - recorded as the episode's error
                result = e
            try:
                if isinstance(result, BaseException):
                    done.set_exception(result)
                else:
                    done.set_result(result)
            except InvalidStateError:  # cancelled meanwhile
                pass

        task.add_done_callback(unpack)
        return done

    def executing(self) -> set[str]:
        """Keys of the tasks the cluster's workers are running now."""
        return {k for keys in self.client.run(_executing_keys).values() for k in keys}

    def reset(self) -> None:
        """Nothing to rebuild: Dask reschedules a lost worker's tasks itself."""

    def close(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def describe(self) -> str:
        where = f"scheduler {self.scheduler}" if self.scheduler else "local cluster on 127.0.0.1"
        return f"Dask, {where}, {self.workers} worker threads"

    def __enter__(self) -> DaskEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def unpack_episode(archive: bytes, episodes_dir: Path, *, name: str) -> None:
    """Unpack a shipped episode folder ``name`` into ``episodes_dir/name`` (replacing
    a stale one). An episode writes only its own folder: every member must be
    ``name`` or ``name/...`` with no ``.``, ``..`` or empty part, and a regular file
    or a folder (no links, devices or FIFOs). It is unpacked into a fresh staging
    folder first (``tarfile``'s ``data`` filter bounding it there) and moved into
    place whole, so a refused archive leaves the episode's previous folder alone.

    Raises:
        tarfile.TarError: the archive is damaged, or holds anything else (another
            episode's folder, an absolute path, ``..``, a link).
    """
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r") as tar:
        members = tar.getmembers()
        strays = [m.name for m in members if not _own(m, name)]
        if strays or not members:
            raise tarfile.TarError(f"an archive for episode folder {name} holds "
                                   f"{', '.join(strays[:3]) if strays else 'nothing'} (only regular files and "
                                   f"folders under {name}/ are accepted)")
        episodes_dir.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=episodes_dir))
        try:
            tar.extractall(staging, members=members, filter="data")
            target = episodes_dir / name
            if target.is_symlink() or target.is_file():
                target.unlink()
            elif target.exists():
                shutil.rmtree(target)
            (staging / name).rename(target)
        finally:
            shutil.rmtree(staging, ignore_errors=True)


def _own(member: tarfile.TarInfo, name: str) -> bool:
    """``member`` is ``name`` itself or a plain path under it, and a file or a folder."""
    parts = member.name.split("/")
    if parts and parts[-1] == "" and member.isdir():
        parts = parts[:-1]  # "e00001/sub/" as some tar writers name folders
    return (parts[0] == name and not any(p in ("", ".", "..") for p in parts)
            and (member.isfile() or member.isdir()))


__all__ = ["DaskEngine", "EngineKind", "ProcessEngine", "shipped_episode", "unpack_episode"]

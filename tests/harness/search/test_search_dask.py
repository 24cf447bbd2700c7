"""Campaigns on a real Dask cluster of worker processes (``hil search --engine dask``):
the same campaign seed gives the same episodes and corner cases as the process pool
and as a sharded run merged, whether the CLI starts its own local cluster or joins a
running one with ``--scheduler``. No mocks: ``distributed.LocalCluster`` with
``processes=True`` (each worker its own process, one thread), on 127.0.0.1."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from hil.harness.search.campaign import run_campaign
from hil.harness.search.merge import merge
from hil.harness.search.spec import load_spec
from tests.conftest import GL_BACKEND
from hil.common.errors import ConfigError

distributed = pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[3]
pytestmark = pytest.mark.slow

SPEC = {"name": "dask-search", "seed": 11, "episodes": 2,
        "run": {"mode": "lockstep", "duration_s": 1.5, "scenario": {"name": "stopped_car"},
                "target": {"command": ["{python}", "-m", "hil.targets.echo", "--throttle", "0.3"]},
                "corner_cases": {"history_s": 0.5, "after_s": 0.2}},
        "params": {"gap_m": [15, 30], "ego_speed_mps": [6, 12]}, "latency": {"ms": [0, 200]},
        "strategy": {"kind": "random"}}


def hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), check=False)


def episodes(folder: Path) -> dict[int, tuple]:
    con = sqlite3.connect(folder / "campaign.sqlite")
    try:
        return {r[0]: r[1:] for r in con.execute("SELECT episode, seed, params, status, trace_hash FROM episodes")}
    finally:
        con.close()


def cases(folder: Path) -> list[tuple]:
    con = sqlite3.connect(folder / "campaign.sqlite")
    try:
        return con.execute("SELECT episode, case_id, vehicle, sim_time_ns, kind, cause, severity, mcap_path FROM "
                           "cases ORDER BY episode, case_id").fetchall()
    finally:
        con.close()


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("spec") / "dask.yaml"
    p.write_text(yaml.safe_dump(SPEC))
    return p


@pytest.fixture(scope="module")
def pooled(spec_file, tmp_path_factory) -> Path:
    """The campaign on the process pool: the reference."""
    out = tmp_path_factory.mktemp("pool") / "pool"
    oc = run_campaign(load_spec(spec_file), out=out, gl_backend=GL_BACKEND, workers=2, install_signal_handlers=False)
    assert oc.complete, [r.error for r in oc.ran]
    return out


@pytest.fixture(scope="module")
def cluster():
    """A running cluster as a user would start one: a scheduler and two worker processes."""
    import dask

    os.environ["MUJOCO_GL"] = GL_BACKEND
    with dask.config.set({"distributed.worker.daemon": False}):
        lc = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=None, silence_logs=40)
    try:
        yield lc
    finally:
        lc.close()


def test_a_local_dask_cluster_runs_the_same_episodes_and_cases_as_the_pool(spec_file, pooled, tmp_path):
    out = tmp_path / "dask"
    p = hil("search", str(spec_file), "--engine", "dask", "--workers", "2", "--out", str(out), "--no-progress")
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert "engine: Dask, local cluster on 127.0.0.1, 2 worker threads" in p.stdout
    assert "Traceback" not in p.stderr
    assert episodes(out) == episodes(pooled) and len(episodes(out)) == 2
    assert all(v[2] == "ok" for v in episodes(out).values())
    got = cases(out)
    assert got and got == cases(pooled), "the same corner cases with the same ids"
    for *_, mcap_path in got:  # shipped back from the worker into this campaign folder
        assert (out / mcap_path).is_file()
    assert (out / "episodes" / "e00001" / "config.json").is_file() and (out / "report.html").is_file()


def test_a_shard_on_a_running_cluster_merges_into_the_pooled_campaign(spec_file, pooled, cluster, tmp_path):
    addr = cluster.scheduler_address
    assert addr.startswith("tcp://127.0.0.1:")
    # One call, over a copy of the names: scheduler_info is refreshed while the client
    # talks to the scheduler (a fresh clone's suite saw it change size in a loop over it).
    pids = cluster.get_client().run(os.getpid)
    assert set(pids) == set(cluster.scheduler_info["workers"]), pids
    assert len(set(pids.values())) == 2 and os.getpid() not in pids.values(), "worker processes, not threads"
    p = hil("search", str(spec_file), "--scheduler", addr, "--shard", "0/2", "--out", str(tmp_path / "s0"),
            "--no-progress")
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert f"scheduler {addr}, 2 worker threads" in p.stdout
    tp = cluster.scheduler.task_prefixes.get("hil-episode")
    assert tp is not None and tp.max_exec_time > 0.5, "the episode ran as a task on the cluster's workers"
    p = hil("search", str(spec_file), "--shard", "1/2", "--workers", "1", "--out", str(tmp_path / "s1"),
            "--no-progress")
    assert p.returncode == 0, (p.stdout, p.stderr)
    r = merge(tmp_path / "merged", [tmp_path / "s0", tmp_path / "s1"])
    assert r.summary["episodes"]["complete"]
    assert episodes(tmp_path / "merged") == episodes(pooled)
    assert cases(tmp_path / "merged") == cases(pooled)


def test_scheduler_mistakes_are_one_line(spec_file, tmp_path):
    from hil.harness.search.executor import DaskEngine

    p = hil("search", str(spec_file), "--engine", "process", "--scheduler", "tcp://127.0.0.1:1",
            "--out", str(tmp_path / "x"))
    assert p.returncode == 2 and "--scheduler tcp://127.0.0.1:1: needs --engine dask" in p.stderr
    assert "Traceback" not in p.stderr and not (tmp_path / "x").exists()
    with pytest.raises(ConfigError, match="--scheduler tcp://127.0.0.1:1: cannot reach the Dask scheduler"):
        DaskEngine(gl_backend=GL_BACKEND, scheduler="tcp://127.0.0.1:1", timeout_s=1.0)


def test_daemonic_workers_are_refused_before_any_episode(spec_file, tmp_path):
    """Dask's default workers are daemonic and may not start an episode's processes:
    said at once, with the setting that fixes it, instead of every episode failing."""
    from hil.harness.search.executor import DaskEngine

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=40) as lc:
        with pytest.raises(ConfigError, match="are daemonic processes.*DASK_DISTRIBUTED__WORKER__DAEMON=False"):
            DaskEngine(gl_backend=GL_BACKEND, scheduler=lc.scheduler_address)


def _tar(entries: dict[str, bytes]) -> bytes:
    import io
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _tar_with(members: list[tuple[str, bytes, str]]) -> bytes:
    """A tar of (name, data, kind): kind "file", "dir", "symlink" (data: its target) or "hardlink"."""
    import io
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data, kind in members:
            info = tarfile.TarInfo(name)
            if kind == "file":
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
                continue
            info.type = {"dir": tarfile.DIRTYPE, "symlink": tarfile.SYMTYPE, "hardlink": tarfile.LNKTYPE}[kind]
            info.linkname = data.decode()
            tar.addfile(info)
    return buf.getvalue()


def test_an_episode_cannot_write_a_sibling_episode(tmp_path):
    # `e00001/../e00000/...` and a symlink to the sibling both stayed inside the episodes
    # folder, so tarfile's data filter let them overwrite another episode (issue 26, item 4).
    import tarfile

    from hil.harness.search.executor import unpack_episode

    eps = tmp_path / "episodes"
    (eps / "e00000").mkdir(parents=True)
    (eps / "e00000" / "summary.json").write_text("episode 0's own")
    (eps / "e00001").mkdir()
    (eps / "e00001" / "run.mcap").write_text("episode 1, first attempt")
    attacks = {
        "traversal": [("e00001/run.mcap", b"x", "file"), ("e00001/../e00000/summary.json", b"forged", "file")],
        "symlink": [("e00001/sib", b"../e00000", "symlink"), ("e00001/sib/summary.json", b"forged", "file")],
        "symlink alone": [("e00001/sib", b"../e00000/summary.json", "symlink")],
        "hardlink": [("e00001/h", b"e00000/summary.json", "hardlink")],
        "dot": [("e00001/./run.mcap", b"x", "file")],
        "empty part": [("e00001//run.mcap", b"x", "file")],
    }
    for what, members in attacks.items():
        with pytest.raises(tarfile.TarError, match="only regular files and folders under e00001/"):
            unpack_episode(_tar_with(members), eps, name="e00001")
        assert (eps / "e00000" / "summary.json").read_text() == "episode 0's own", what
        assert (eps / "e00001" / "run.mcap").read_text() == "episode 1, first attempt", what  # left whole
    assert sorted(p.name for p in eps.iterdir()) == ["e00000", "e00001"]  # no staging folder left
    unpack_episode(_tar_with([("e00001", b"", "dir"), ("e00001/sub/", b"", "dir"), ("e00001/sub/a", b"a", "file"),
                              ("e00001/run.mcap", b"new", "file")]), eps, name="e00001")
    assert (eps / "e00001" / "run.mcap").read_text() == "new" and (eps / "e00001" / "sub" / "a").is_file()


def _listening_ports(pids: set[int]) -> set[tuple[str, int]]:
    """(address, port) of every TCP socket in LISTEN state owned by ``pids`` (from /proc)."""
    inodes: set[str] = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            try:
                link = os.readlink(fd)
            except OSError:
                continue
            if link.startswith("socket:["):
                inodes.add(link[8:-1])
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # 0A: LISTEN
                addr, port = f[1].rsplit(":", 1)
                host = ".".join(str(int(addr[i:i + 2], 16)) for i in (6, 4, 2, 0)) if len(addr) == 8 else addr
                out.add((host, int(port, 16)))
    return out


def test_a_foreign_client_is_refused_and_nothing_serves_8787():
    # Any local process could connect a distributed.Client to the campaign's scheduler
    # and run code in it, and an HTTP server answered on 127.0.0.1:8787 (issue 26, item 4).
    from distributed.security import Security

    from hil.harness.search.executor import DaskEngine

    with DaskEngine(gl_backend=GL_BACKEND, workers=1) as eng:
        addr = eng._cluster.scheduler_address
        assert addr.startswith("tls://127.0.0.1:")
        assert eng.client.submit(lambda x: x + 1, 1).result() == 2  # the campaign's own client works
        plain = "tcp://" + addr.removeprefix("tls://")
        for target, security in ((plain, None), (addr, Security.temporary()), (addr, None)):
            with pytest.raises((OSError, TypeError, distributed.comm.core.CommClosedError)):
                distributed.Client(target, security=security, timeout=3)
        # The scheduler and the nannies live in this process (beside any other cluster a
        # test of this module started): their own sockets; the workers are processes.
        from distributed.comm.utils import get_tcp_server_addresses

        sched = eng._cluster.scheduler
        ports = {tuple(a) for a in get_tcp_server_addresses(sched.http_server)}
        workers = set(eng.client.run(os.getpid).values()) - {os.getpid()}
        ports |= _listening_ports(workers)
        assert workers and ports and all(host == "127.0.0.1" for host, _ in ports), ports
        assert 8787 not in {port for _, port in ports}, ports
        http = sched.http_server.port
        import urllib.error
        import urllib.request

        for route in ("/status", "/info/main/workers.html", "/health", "/metrics", "/json/identity.json"):
            with pytest.raises(urllib.error.HTTPError) as no:
                urllib.request.urlopen(f"http://127.0.0.1:{http}{route}", timeout=3)
            assert no.value.code == 404, route


def test_a_shipped_episode_unpacks_only_into_its_own_folder(tmp_path):
    import tarfile

    from hil.harness.search.executor import unpack_episode

    eps = tmp_path / "campaign" / "episodes"
    (eps / "e00003").mkdir(parents=True)
    (eps / "e00003" / "stale.txt").write_text("an interrupted attempt")
    (tmp_path / "campaign" / "campaign.sqlite").write_text("keep")
    unpack_episode(_tar({"e00003/run.mcap": b"mcap", "e00003/config.json": b"{}"}), eps, name="e00003")
    assert sorted(p.name for p in (eps / "e00003").iterdir()) == ["config.json", "run.mcap"]
    for bad, says in [({"e00004/run.mcap": b"x"}, "e00004/run.mcap"), ({"../campaign.sqlite": b"x"}, "\\.\\./"),
                      ({"e00003/ok": b"x", "/etc/x": b"x"}, "/etc/x"), ({}, "nothing")]:
        with pytest.raises(tarfile.TarError, match=f"episode folder e00003 holds .*{says}"):
            unpack_episode(_tar(bad), eps, name="e00003")
    with pytest.raises(tarfile.TarError):  # a member escaping through .. inside the folder
        unpack_episode(_tar({"e00003/../../campaign.sqlite": b"x"}), eps, name="e00003")
    assert (tmp_path / "campaign" / "campaign.sqlite").read_text() == "keep" and not (eps / "e00004").exists()


def test_the_local_cluster_is_worker_processes_on_loopback_only():
    from hil.harness.search.executor import DaskEngine

    with DaskEngine(gl_backend=GL_BACKEND, workers=2) as eng:
        sched = eng._cluster.scheduler
        assert sched.address.startswith("tls://127.0.0.1:")
        info = eng.client.scheduler_info()
        assert all(w.startswith("tls://127.0.0.1:") for w in info["workers"]), info["workers"]
        assert sorted(eng.client.nthreads().values()) == [1, 1] and eng.workers == 2
        pids = eng.client.run(os.getpid)
        assert len(set(pids.values())) == 2 and os.getpid() not in pids.values()
        assert not any(eng.client.run(lambda: __import__("multiprocessing").current_process().daemon).values())


def test_sigterm_lets_running_episodes_finish_and_resume_completes(spec_file, tmp_path):
    out = tmp_path / "stopped"
    cmd = [sys.executable, "-m", "hil.harness.cli.main", "search", str(spec_file), "--engine", "dask", "--workers", "1",
           "--out", str(out), "--no-progress", "--episodes", "4"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, MUJOCO_GL=GL_BACKEND))
    try:
        for line in proc.stdout:  # the first episode is back: the second is running, the third queued
            if line.startswith("e0000"):
                proc.terminate()
                break
        rest, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, (rest, err)
    assert "stopped" in rest and "--resume" in rest and "Traceback" not in err
    done = episodes(out)
    # What ran when SIGTERM came finished and was kept, what was queued was dropped. Which
    # episode was running depends on the machine's pace (e00001 usually; e00002 when
    # e00001 ended before the signal landed): one worker runs them in order, so the
    # kept ones are e00000..e0000k, all whole, and not all four.
    assert sorted(done) == list(range(len(done))) and 1 <= len(done) < 4, done
    assert all(v[2] == "ok" for v in done.values()), done
    for i in done:
        assert (out / "episodes" / f"e{i:05d}" / "run.mcap").is_file()
    p = hil("search", str(spec_file), "--engine", "dask", "--workers", "2", "--out", str(out), "--no-progress",
            "--episodes", "4", "--resume")
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert f"4 episodes, {len(done)} done already" in p.stdout and sorted(episodes(out)) == [0, 1, 2, 3]


def test_a_queued_episode_cancelled_is_dropped_not_an_error(spec_file, tmp_path):
    # A stopped campaign cancels the episodes no worker runs yet. Dask runs the task's
    # callback on its own thread, often before task.cancel() returns: it found the
    # episode's future not yet cancelled and gave it the task's CancelledError, so the
    # campaign recorded a queued episode as an error (a fresh-clone suite saw e00001
    # "error" after SIGTERM). One worker: the first episode runs, the next three wait.
    from hil.harness.search.executor import DaskEngine
    from hil.harness.search.sampling import draw_generation

    c = load_spec(spec_file, episodes=4)
    draws = draw_generation(c, 0)
    assert len(draws) == 4
    with DaskEngine(gl_backend=GL_BACKEND, workers=1) as engine:
        futures = [engine.submit(c, d, out=tmp_path, shard="0/1") for d in draws]
        queued = futures[1:]
        assert all(f.cancel() for f in queued), [f.exception() if f.done() and not f.cancelled() else f
                                                 for f in queued]
        assert all(f.cancelled() for f in queued)
        first = futures[0].result(timeout=120)
    assert first.status == "ok" and first.index == draws[0].index

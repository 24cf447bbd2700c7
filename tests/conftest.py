"""Shared fixtures. MuJoCo's GL backend is fixed when ``mujoco`` is first imported,
so it is chosen here, before any test module imports the simulator."""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import jsonschema
import pytest

from hil.harness.vocab.events import EVENT_SCHEMA
from hil.scenarios.gl import select_backend

GL_BACKEND = select_backend()
T = TypeVar("T")


def in_child_processes(fn: Callable[..., T], calls: Sequence[tuple[Any, ...]], *, at_most: int = 4) -> list[T]:
    """``[fn(*args) for args in calls]``, computed in child processes, as many at once as
    this machine has cores (``at_most``): the results, in the calls' order, are what the
    loop would return. Only for deterministic, CPU-bound work whose results do not depend
    on timing (lockstep runs, in-process closed loops): never for real-time runs, which
    would load each other. ``fn`` and its arguments must be importable by name (a
    module-level function); the children are spawned, not forked, so nothing of this
    process (threads, GL contexts) is copied into them. A failure in a child is raised here."""
    workers = max(1, min(at_most, len(os.sched_getaffinity(0)), len(calls)))
    if workers == 1:
        return [fn(*args) for args in calls]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(fn, *zip(*calls)))


# --- work computed ahead, beside the tests before it ------------------------------------
# A few fixtures are deterministic, CPU-bound work that reads no clock for what it is
# judged on (the in-process closed loops, the CNN's held-out frames, lockstep runs whose
# frames and target start time out only past what starvation can reach): their results are
# the same whenever and beside whatever they run. Such a fixture registers its calls with
# ``ahead`` when its module is imported; once the session's tests are collected, the calls
# start in child processes at nice 19 and the fixture takes the results with
# ``ahead_results``, waiting for what is left. Nice 19: a test's process that wants a
# core takes it from them at once, so a real-time test beside them runs much as on a
# quiet machine, yet they keep a sliver of each core (SCHED_IDLE could starve them for
# good); a run raises its threads' priority relative to the nice value it started at
# (hil.adapters.process), so it stays in the background. A lockstep run with the default
# estimate timeout (0.5 s) is no such work: starved, it drops frames.
_AHEAD: dict[str, tuple[Callable[..., Any], list[tuple[Any, ...]]]] = {}
_AHEAD_ROOT = Path(tempfile.gettempdir()) / f"hil-tests-ahead-{os.getpid()}"
_AHEAD_STARTED: dict[str, list[Any]] = {}
_AHEAD_POOL: list[ProcessPoolExecutor] = []


# A lockstep run's target settings when it runs ahead: its start and each frame time out
# only past what no starvation reaches (its results do not depend on how long it waited).
AHEAD_TIMEOUTS = {"estimate_timeout_s": 30.0, "startup_timeout_s": 120.0}


def ahead(module: str, fixture: str, fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> None:
    """Compute ``[fn(*args) for args in calls]`` ahead for ``module``'s ``fixture``
    (``fn`` and its arguments importable by name, as for ``in_child_processes``)."""
    _AHEAD[f"{module}::{fixture}"] = (fn, list(calls))


def ahead_folder(name: str) -> Path:
    """A folder for a call of ``ahead`` to write into (the call creates it), removed
    when the session ends."""
    return _AHEAD_ROOT / name


def ahead_results(module: str, fixture: str) -> list[Any]:
    """The results of what ``ahead`` (or ``beside``) registered, in the calls' order;
    computed here, as ``in_child_processes`` does (``beside``: in this process), when the
    session did not start them."""
    key = f"{module}::{fixture}"
    futures = _AHEAD_STARTED.pop(key, None)
    if futures is not None:
        return [f.result() for f in futures]
    if key in _BESIDE:
        fn, args, kwargs = _BESIDE[key]
        return [fn(*args, **kwargs)]
    fn, calls = _AHEAD[key]
    return in_child_processes(fn, calls)


def _lowest_priority() -> None:
    os.nice(19)


# --- real-time runs beside the tests ----------------------------------------------------
# A few real-time runs are judged on the machine as it is: the clean calibration holds
# every anomaly against the reference target's own truth, so a delay the machine causes
# (the target or the harness preempted) is explained, and only a false alarm fails it; the
# demo is judged on where the car stops, a tiny study on what its points wrote and how
# they compare. They run in a child process at the session's own priority (not nice 19:
# they must keep real time), started before any test; each fixture takes its result,
# waiting for what is left. A run whose verdict needs a quiet machine is no such work
# (runs with injected faults are not: a loaded machine widens the spike detector's
# baseline). One at a time, in the order their modules are collected: runs beside each
# other would load each other past what a test beside them does. The three (~65 + 16 +
# 14 s) end within the first folders of tests (tests/adapters, ~115 s here).
_BESIDE: dict[str, tuple[Callable[..., Any], tuple[Any, ...], dict[str, Any]]] = {}


def beside(module: str, fixture: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
    """Run ``fn(*args, **kwargs)`` (importable by name) in real time beside the tests,
    for ``module``'s ``fixture``; ``ahead_results`` returns ``[fn(*args, **kwargs)]``."""
    _BESIDE[f"{module}::{fixture}"] = (fn, args, kwargs)


def pytest_collection_finish(session: pytest.Session) -> None:
    wanted = set()
    for item in session.items:
        module = getattr(item, "module", None)
        for name in getattr(item, "fixturenames", ()) if module is not None else ():
            if f"{module.__name__}::{name}" in _AHEAD or f"{module.__name__}::{name}" in _BESIDE:
                wanted.add(f"{module.__name__}::{name}")
    if session.config.option.collectonly:
        return
    spawn = multiprocessing.get_context("spawn")
    # Alone in the session it runs as the fixture asks (in this process): nothing to be beside.
    real_time = [k for k in _BESIDE if k in wanted] if len(session.items) > 1 else []
    if real_time:  # first: it keeps real time from its start
        pool = ProcessPoolExecutor(1, mp_context=spawn)
        _AHEAD_POOL.append(pool)
        for key in real_time:
            fn, args, kwargs = _BESIDE[key]
            _AHEAD_STARTED[key] = [pool.submit(fn, *args, **kwargs)]
    computed = [k for k in _AHEAD if k in wanted]
    if computed:
        pool = ProcessPoolExecutor(max(1, min(4, len(os.sched_getaffinity(0)))), mp_context=spawn,
                                   initializer=_lowest_priority)
        _AHEAD_POOL.append(pool)
        for key in computed:
            fn, calls = _AHEAD[key]
            _AHEAD_STARTED[key] = [pool.submit(fn, *args) for args in calls]


def pytest_sessionfinish(session: pytest.Session) -> None:
    for pool in _AHEAD_POOL:
        pool.shutdown(wait=True, cancel_futures=True)
    shutil.rmtree(_AHEAD_ROOT, ignore_errors=True)


def recording_started(mcap: Path) -> bool:
    """A running run's recorder has flushed once: it flushes each second, and its first
    flush (~50 KB for the demo) holds the first second's frames and answers (the file's
    header alone is 61 bytes)."""
    return mcap.exists() and mcap.stat().st_size > 20_000


def read_mcap(path: Path) -> dict[str, list[tuple[Any, Any]]]:
    """All messages of an MCAP file by topic: (message record, decoded JSON)."""
    from mcap.reader import make_reader

    out: dict[str, list[tuple[Any, Any]]] = defaultdict(list)
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            assert schema is not None and schema.encoding == "jsonschema", channel.topic
            d = json.loads(message.data)
            if channel.topic == "/events":  # every event, in every test that reads one, against its one schema
                assert json.loads(schema.data)["required"] == EVENT_SCHEMA["required"], "not the event schema"
                jsonschema.validate(d, json.loads(schema.data))
            out[channel.topic].append((message, d))
    return out


@pytest.fixture
def gl_backend() -> str:
    return GL_BACKEND

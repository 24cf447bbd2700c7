"""The harness raises its latency-critical threads' priority relative to the nice value
it was started at and gives it back as it was: ``nice -n 10 hil search ...`` stays
below the user's other work (before, a run set its loop thread to nice -5 and, at its
end, to 0, whatever the user had asked for)."""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from hil.adapters.process import prioritise_this_thread, restore_thread_priority
from hil.harness.engine.procs import lower_thread_priority
from tests.conftest import GL_BACKEND


def _nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


def _in_a_thread_at(nice: int, fn) -> list[object]:  # type: ignore[no-untyped-def]
    out: list[object] = []

    def body() -> None:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        out.extend(fn())

    t = threading.Thread(target=body)
    t.start()
    t.join()
    return out


def test_a_boost_is_relative_and_given_back() -> None:
    def boost() -> list[object]:
        before = prioritise_this_thread()
        during = _nice()
        if before is not None:
            restore_thread_priority(before)
        return [before, during, _nice()]

    before, during, after = _in_a_thread_at(7, boost)
    assert after == 7
    if before is None:  # no CAP_SYS_NICE: nothing changed
        assert during == 7
    else:
        assert before == 7 and during == 2


def test_a_thread_that_yields_goes_above_its_nice_up_to_19() -> None:
    assert _in_a_thread_at(3, lambda: (lower_thread_priority(), _nice())[1:]) == [13]
    assert _in_a_thread_at(15, lambda: (lower_thread_priority(), _nice())[1:]) == [19]


def _lockstep_run_at_nice(nice: int, out: str) -> int:
    from hil.harness.config.loading import parse_config
    from hil.harness.run.driver import execute, prepare_out_dir

    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    cfg = parse_config({"name": "nice", "mode": "lockstep", "duration_s": 0.5, "progress": False,
                        "target": {"command": [sys.executable, "-m", "hil.targets.echo"]}})
    execute(cfg, out_dir=prepare_out_dir(Path(out)), gl_backend=GL_BACKEND, install_signal_handlers=False)
    return _nice()


def test_a_run_started_at_nice_10_ends_at_nice_10(tmp_path) -> None:
    # In a child process: the run's loop thread is its main thread.
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        assert pool.submit(_lockstep_run_at_nice, 10, str(tmp_path / "run")).result(timeout=120) == 10

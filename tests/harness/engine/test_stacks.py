"""SIGUSR2 prints a harness process's stacks and leaves it running (README, "A run
that seems stuck"): what a stuck run is doing, read without stopping it."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

CHILD = """
import threading, time, sys
from hil.harness.engine.procs import die_with_parent

def parked_in_a_named_function():
    time.sleep(30)

threading.Thread(target=parked_in_a_named_function, daemon=True).start()
die_with_parent()  # what every child of the harness calls first
print("ready", flush=True)
for line in sys.stdin:
    print("still running", flush=True)
    break
"""


def test_sigusr2_prints_every_threads_stack_and_the_process_goes_on() -> None:
    p = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout is not None and p.stdin is not None
        assert p.stdout.readline() == "ready\n"
        time.sleep(0.1)  # the thread is in its sleep
        p.send_signal(signal.SIGUSR2)
        time.sleep(0.3)
        p.stdin.write("go on\n")
        p.stdin.flush()
        assert p.stdout.readline() == "still running\n"  # SIGUSR2's default would have ended it
        _, err = p.communicate(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, err
    assert "in parked_in_a_named_function" in err and "Current thread" in err, err


def test_without_a_standard_error_nothing_is_registered_and_nothing_fails(monkeypatch) -> None:
    # A harness child must start whatever its stderr is (stacks_on_sigusr2 runs first in
    # each): None (closed) or an object without a file descriptor (an embedding's).
    import io

    from hil.harness.engine.procs import stacks_on_sigusr2

    for err in (None, io.StringIO()):
        monkeypatch.setattr(sys, "stderr", err)
        stacks_on_sigusr2()  # no exception

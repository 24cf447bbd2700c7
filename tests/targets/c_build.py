"""Builds the C reference target (targets/c) once per test session with the system C
compiler: the plain binary (-O2) and the AddressSanitizer + UBSan one, both with
``-Wall -Wextra -Werror``."""

from __future__ import annotations

import atexit
import functools
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "targets" / "c"
# A sanitizer report makes the program exit non-zero (-fno-sanitize-recover=all);
# these options also keep ASan from needing ptrace and make leaks errors.
SAN_ENV = {"ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0:exitcode=86",
           "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1:exitcode=87"}
SAN_MARKERS = ("ERROR: AddressSanitizer", "runtime error:", "ERROR: LeakSanitizer")


def unavailable() -> str | None:
    """Why the C target cannot be built here, or None."""
    for tool in ("cc", "make"):
        if shutil.which(tool) is None:
            return f"no `{tool}` on PATH: the C reference target is built with the system C compiler"
    return None


@dataclass(frozen=True)
class CBinaries:
    plain: Path
    asan: Path


@functools.lru_cache(maxsize=1)
def build() -> CBinaries:
    """``make all asan`` into a fresh temporary folder.

    Raises:
        AssertionError: the build failed (with the compiler's output).
    """
    out = Path(tempfile.mkdtemp(prefix="hil-c-target-"))
    atexit.register(shutil.rmtree, out, True)
    proc = subprocess.run(["make", "-s", "-C", str(SOURCE), f"BUILD={out}", "all", "asan"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"make failed:\n{proc.stdout}\n{proc.stderr}"
    return CBinaries(out / "hil_target", out / "hil_target_asan")


def sanitizer_report(log_text: str) -> str | None:
    """The first sanitizer line in a target's log, or None."""
    for line in log_text.splitlines():
        if any(m in line for m in SAN_MARKERS):
            return line
    return None

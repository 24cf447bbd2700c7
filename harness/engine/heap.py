"""Keep the run process's heap from creeping through a long run (glibc malloc).

glibc serves an allocation of at least ``M_MMAP_THRESHOLD`` bytes with its own
``mmap`` and gives it back on free; smaller ones come from the heap of the thread's
arena. The threshold is dynamic by default: after the first such block is freed it
rises to that block's size (up to 32 MiB). The run process frees a camera frame's
bytes (~230 KB raw at 320x240), an MCAP chunk (~280 KB) and its compressed copy many
times a second, so after the first the threshold climbs past them and they are cut
from the arenas' heaps, where blocks of ever so slightly different sizes left holes
that stayed resident: a 10-minute demo run grew by ~0.3 MB/min with every Python-level
column already spilled to disk. A fixed threshold (setting it turns the dynamic rule
off) keeps such blocks out of the heaps: 5-minute run, +0.15 MB/min
(``bench/bench_soak.py``). The cost is an ``mmap``/``munmap`` pair per large block,
a few per frame.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_MMAP_THRESHOLD = -3  # mallopt's parameter number (glibc malloc.h)
MMAP_THRESHOLD = 128 * 1024  # glibc's own starting value, now kept


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``nbytes`` for this process (module docstring).
    True when set; False where the C library is not glibc (nothing changes there)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, nbytes))

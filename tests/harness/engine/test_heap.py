"""The run process keeps glibc's mmap threshold fixed (hil.harness.engine.heap): a
large block freed no longer moves the threshold up, so later large blocks are still
mapped on their own, not cut from a heap where their holes stay resident."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = r"""
import ctypes, sys
from hil.harness.engine.heap import fix_mmap_threshold

libc = ctypes.CDLL("libc.so.6")
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
if sys.argv[1] == "fixed":
    assert fix_mmap_threshold()
# A freed mapped block: glibc's dynamic rule raises the threshold to its size. A block
# is mapped only where the heap's free top cannot hold it (what the interpreter's start
# left there varies): give the top back first, and take the first size that is mapped.
libc.malloc_trim(0)
for mib in (4, 8, 16, 30):  # the rule moves the threshold up to 32 MiB at most
    h = libc.mallinfo2().hblks
    big = libc.malloc(mib << 20)
    mapped = libc.mallinfo2().hblks == h + 1
    libc.free(big)
    if mapped:
        break
else:
    sys.exit("no block of 4-30 MiB was mapped")
before = libc.mallinfo2().hblks
block = libc.malloc(300_000)  # an MCAP chunk's size
print(libc.mallinfo2().hblks - before)
libc.free(block)
"""


def _mapped_blocks(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return int(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc")
def test_large_blocks_stay_mapped_after_a_larger_one_was_freed():
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").mallinfo2  # noqa: B018 - glibc >= 2.33
    except (OSError, AttributeError):
        pytest.skip("not glibc >= 2.33")
    assert _mapped_blocks("default") == 0  # the dynamic rule: cut from the heap
    assert _mapped_blocks("fixed") == 1

"""SpillColumn: exact columns of any length in bounded memory (issue 14 item 12)."""

from __future__ import annotations

import os
import tracemalloc

import numpy as np
import pytest

from hil.timing.stats import SpillColumn, SpillFile, summarize_ns


def test_values_come_back_exactly_and_in_order(tmp_path) -> None:
    spill = SpillFile(str(tmp_path))
    rng = np.random.default_rng(7)
    want = rng.integers(-2**62, 2**62, size=10_000, dtype=np.int64)
    col = SpillColumn(block=64, spill=spill)
    for v in want.tolist():
        col.append(v)
    assert len(col) == 10_000 and col
    assert np.array_equal(col.to_numpy(), want)
    assert list(col)[:5] == want[:5].tolist()
    assert summarize_ns(col) == summarize_ns(want.tolist())
    spill.close()


def test_spill_file_is_unlinked_and_shared(tmp_path) -> None:
    spill = SpillFile(str(tmp_path))
    a, b = SpillColumn(block=4, spill=spill), SpillColumn(block=4, spill=spill)
    for i in range(10):
        a.append(i)
        b.append(-i)
    assert os.listdir(tmp_path) == []  # nothing left behind, whatever way the process ends
    assert a.to_numpy().tolist() == list(range(10)) and b.to_numpy().tolist() == [-i for i in range(10)]
    spill.close()


def test_memory_stays_flat_while_the_column_grows(tmp_path) -> None:
    spill = SpillFile(str(tmp_path))
    col = SpillColumn(block=1024, spill=spill)
    tracemalloc.start()
    try:
        for i in range(20_000):
            col.append(i)
        early, _ = tracemalloc.get_traced_memory()
        for i in range(200_000):
            col.append(i)
        late, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # 200k more values are 1.6 MB of int64; in memory only the offsets list grows (~200 entries).
    assert late - early < 40_000, (early, late)
    assert len(col) == 220_000
    spill.close()


def test_a_block_that_cannot_be_spilled_stays_in_memory_and_is_counted(tmp_path) -> None:
    class FullDisk(SpillFile):
        def write(self, block: np.ndarray) -> int:
            raise OSError(28, "No space left on device")

    col = SpillColumn(block=3, spill=FullDisk(str(tmp_path)))
    for i in range(8):
        col.append(i)
    assert col.spill_failures == 2
    assert col.to_numpy().tolist() == list(range(8))


def test_block_must_be_positive() -> None:
    with pytest.raises(ValueError, match="block"):
        SpillColumn(block=0)


def test_a_forked_child_gets_its_own_default_spill_file() -> None:
    from hil.timing import stats

    parent = stats.default_spill()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: a fresh file, not the parent's offsets
        os.write(w, b"1" if stats.default_spill() is not parent else b"0")
        os._exit(0)
    os.close(w)
    os.waitpid(pid, 0)
    assert os.read(r, 1) == b"1"
    os.close(r)
    assert stats.default_spill() is parent

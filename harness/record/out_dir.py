"""Claiming a run folder: one run per folder, and only where its bytes fit.

``claim_out_dir`` (what ``hil.harness.run.driver.prepare_out_dir`` does) creates the folder,
takes an exclusive ``flock`` on ``OUT/.hil-run.lock`` and probes the disk with real
bytes. The lock is the kernel's: it goes away when this process exits, however it
exits (SIGKILL included), so a crashed run never leaves a stale claim behind. A
second run on the same folder while the first holds it is refused; a run that
finished is refused by its ``run.mcap``.

A process that runs many runs (a search worker, a test session) gives a claim back
with ``release_out_dir``; claims of runs that wrote their ``summary.json`` are
also given back by the next ``claim_out_dir``, so they never pile up.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from hil.common.errors import ConfigError

__all__ = ["LOCK_NAME", "PROBE_BYTES", "claim_out_dir", "held_claims", "release_out_dir"]

LOCK_NAME = ".hil-run.lock"
PROBE_NAME = ".write-test"
# An empty file fits on a full disk: the probe writes (and syncs) real bytes, about
# what the run writes before its first second of recording.
PROBE_BYTES = 1 << 20
_DONE_MARKER = "summary.json"
FAILED_NAME = "FAILED"  # written by ``hil run`` when a run never produced its summary


class _Claims:
    """The lock descriptors this process holds, by resolved folder."""

    def __init__(self) -> None:
        self.fds: dict[Path, int] = {}


_CLAIMS = _Claims()  # process-wide like the flocks it mirrors (a lock is the process's)


def held_claims() -> list[Path]:
    """The folders this process holds a claim on (resolved paths)."""
    return list(_CLAIMS.fds)


def release_out_dir(out: Path) -> None:
    """Give back this process's claim on ``out`` (no-op when it holds none)."""
    fd = _CLAIMS.fds.pop(Path(out).resolve(), None)
    if fd is not None:
        os.close(fd)  # closing the descriptor drops the flock


def _release_finished() -> None:
    for folder in [f for f in _CLAIMS.fds if (f / _DONE_MARKER).exists()]:
        release_out_dir(folder)


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return "another run"
    return f"another run (pid {text})" if text.isdigit() else "another run"


def claim_out_dir(out: Path) -> Path:
    """Create the run folder ``out``, claim it for this process and probe that
    ``PROBE_BYTES`` can be written there. Returns ``out``.

    Raises:
        ConfigError: one line: the folder holds a finished run, another run holds
            it now, or it cannot be created or written (read-only, full disk, no
            permission).
    """
    _release_finished()
    if (out / "run.mcap").exists():
        raise ConfigError(f"--out {out}: holds a run already (run.mcap exists); choose another folder")
    key = out.resolve() if out.exists() else None
    if key is not None and key in _CLAIMS.fds:
        raise ConfigError(f"--out {out}: a run of this process is writing there; choose another folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as err:
        raise ConfigError(f"--out {out}: cannot write there: {err.strerror or err}") from err
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        who = _holder(fd)
        os.close(fd)
        raise ConfigError(f"--out {out}: {who} is writing there now; wait for it or choose another "
                          f"folder") from err
    try:
        if (out / "run.mcap").exists():  # finished between the first check and the lock
            raise ConfigError(f"--out {out}: holds a run already (run.mcap exists); choose another folder")
        _probe(out)
        (out / FAILED_NAME).unlink(missing_ok=True)  # an earlier failed start's note: this run starts afresh
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
    except BaseException:
        os.close(fd)
        raise
    _CLAIMS.fds[out.resolve()] = fd
    return out


def _probe(out: Path) -> None:
    probe = out / PROBE_NAME
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * PROBE_BYTES)
            f.flush()
            os.fsync(f.fileno())
    except OSError as err:
        reason = err.strerror or str(err)
        raise ConfigError(f"--out {out}: cannot write there: {reason} ({PROBE_BYTES // 1024} KiB probe)") from err
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()

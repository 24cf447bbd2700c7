"""The CAN bus traffic of a run in python-can's log formats, beside ``run.mcap``:
``run.blf`` (Vector BLF: CANoe, CANalyzer, ``python -m can.logconvert``,
``python -m can.player``) or ``run.asc`` (Vector ASCII), per ``recording.can_log``.

Every frame the harness's CAN links send or receive (each vehicle's, its own id
bits; both directions, ``is_rx`` set on received ones) is written with the stamp the
link took on the harness clock, put on the wall clock exactly as the MCAP's
``log_time`` is: ``timestamp = (t_ns + log_time_offset_ns) / 1e9`` with the run's
``time_anchor``. So an estimate's last frame in the log carries the same instant as
its ``t0'`` in ``/<vehicle>/pipeline`` (log time ``t0' + log_time_offset_ns``), and a
SYNC_RESPONSE frame the same as its ``t4`` on ``/<vehicle>/clock_sync``. Precision:
BLF stores nanoseconds from a start time with millisecond resolution (held on a
whole millisecond here), read back as a float (~0.25 µs at today's epoch); ASC
writes microseconds from its ``Begin Triggerblock`` date, which starts on a whole
second here (an opening event), so both read back as absolute times within 1 µs.

The links' threads hand frames over through a bounded queue to one writer thread:
a log that cannot keep up drops frames, counted (``dropped``), never the run's pace.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from can.io.generic import MessageWriter

QUEUE_FRAMES = 200_000


class CanLogFormat(str, Enum):
    BLF = "blf"
    ASC = "asc"
    NONE = "none"


@dataclass
class CanLogStats:
    frames: int = 0
    dropped: int = 0
    error: str | None = None


class CanTrafficLog:
    """Write the CAN frames tapped from the links (``tap_for``) to ``path`` (``.blf``
    or ``.asc``, by suffix) with timestamps on the MCAP's wall-clock timeline
    (``offset_ns``: the recorder's ``log_time_offset_ns``). A context manager;
    ``close`` flushes and is idempotent.

    Raises:
        ConfigError: ``path`` has another suffix.
    """

    def __init__(self, path: Path, *, offset_ns: int, start_ns: int) -> None:
        import can

        from hil.common.errors import ConfigError

        if path.suffix not in (".blf", ".asc"):
            raise ConfigError(f"CAN log {path}: expected a .blf or .asc file")
        self.path, self.offset_ns = path, offset_ns
        self.stats = CanLogStats()
        writer = can.Logger(str(path))
        # Both formats keep their start with millisecond precision: start on a whole
        # millisecond (BLF), a whole second for ASC (python-can 4.6 writes the date's
        # milliseconds unpadded, ".78" for 78 ms, which its reader takes for 780 ms).
        if isinstance(writer, can.ASCWriter):
            writer.log_event("hil: timestamps are the harness clock on the wall clock, as run.mcap's log_time",
                             timestamp=float((start_ns + offset_ns) // 1_000_000_000))
        elif isinstance(writer, can.BLFWriter):
            writer.start_timestamp = (start_ns + offset_ns) // 1_000_000 / 1000
        self._writer: MessageWriter = writer
        self._q: queue.Queue[tuple[Any, int, bool] | None] = queue.Queue(maxsize=QUEUE_FRAMES)
        self._closed = False
        self._thread = threading.Thread(target=self._write_loop, name="can-log", daemon=True)
        self._thread.start()

    def tap(self, msg: Any, t_ns: int, is_rx: bool) -> None:
        """A frame sent or received at ``t_ns`` (harness clock); never blocks."""
        try:
            self._q.put_nowait((msg, t_ns, is_rx))
        except queue.Full:
            self.stats.dropped += 1

    def _write_loop(self) -> None:
        import can

        done = False
        while not done:
            # What is waiting, in time order: frames tapped on two threads may enqueue a
            # few µs out of order (ASC rewrites a timestamp earlier than the last one).
            batch = [self._q.get()]
            while len(batch) < 4096 and not self._q.empty():
                batch.append(self._q.get_nowait())
            done = None in batch
            for msg, t_ns, is_rx in sorted((x for x in batch if x is not None), key=lambda x: x[1]):
                self._write(can, msg, t_ns, is_rx)

    def _write(self, can: Any, msg: Any, t_ns: int, is_rx: bool) -> None:
        if self.stats.error is not None:
            self.stats.dropped += 1
            return
        out = can.Message(timestamp=(t_ns + self.offset_ns) / 1e9, arbitration_id=msg.arbitration_id,
                          is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                          is_error_frame=msg.is_error_frame, channel=0, dlc=msg.dlc, data=bytes(msg.data),
                          is_fd=msg.is_fd, is_rx=is_rx, bitrate_switch=msg.bitrate_switch,
                          error_state_indicator=msg.error_state_indicator)
        try:
            self._writer.on_message_received(out)
            self.stats.frames += 1
        except (OSError, ValueError) as err:  # a full disk: count what is lost, keep the run
            self.stats.error = f"{type(err).__name__}: {err}"
            self.stats.dropped += 1

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join(timeout=30.0)
        try:
            self._writer.stop()
        except (OSError, ValueError) as err:
            self.stats.error = self.stats.error or f"{type(err).__name__}: {err}"

    def summary(self, run_dir: Path) -> dict[str, Any]:
        """``summary.json``'s ``can_log``: the file (relative to the run folder),
        frames written, frames dropped, and the error that stopped it, if any."""
        return {"file": str(self.path.relative_to(run_dir)) if self.path.is_relative_to(run_dir) else str(self.path),
                "frames": self.stats.frames, "dropped": self.stats.dropped, "error": self.stats.error,
                "clock": "harness clock on the wall clock (run.mcap log_time)"}

    def __enter__(self) -> CanTrafficLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_can_log(cfg: Any, out_dir: Path, *, offset_ns: int, now_ns: int) -> CanTrafficLog | None:
    """The run's CAN log (``out_dir/run.blf`` or ``run.asc``) when its transport has
    a CAN half and ``recording.can_log`` is not ``none``; else None. ``now_ns``: the
    harness clock now (the log starts at or before every frame)."""
    fmt = CanLogFormat(cfg.recording.can_log)
    if fmt is CanLogFormat.NONE or cfg.target.transport.value not in ("can", "mixed"):
        return None
    return CanTrafficLog(out_dir / f"run.{fmt.value}", offset_ns=offset_ns, start_ns=now_ns)


__all__ = ["CanLogFormat", "CanLogStats", "CanTrafficLog", "open_can_log"]

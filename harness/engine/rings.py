"""Rings the physics process writes into and never waits on.

A :class:`Ring` is one producer's and one consumer's queue of byte records in shared
memory, with a doorbell: a non-blocking pipe that carries, for each record, the
ring's new write position (8 bytes). The producer copies the record into the ring
and writes the doorbell; both return at once. When the ring has no room for a
record, the record is dropped and counted (``dropped``, also kept in the ring's
header where the consumer's owner reads it at any time): the producer never waits
for a consumer that fell behind, so the consumer's backlog can never show up as
physics lateness (DESIGN.md "Processes: who keeps time").

Ordering. The consumer reads a record only up to a write position it took from the
doorbell, never from shared memory: the producer's copy of the record precedes its
``write`` of the position in program order, and the kernel's pipe (a lock taken by
both the writing and the reading system call) orders that copy before the
consumer's ``read``, on any CPU (no reliance on x86's store order). A doorbell that
finds the pipe full (the consumer is 8,192 records behind) is written again with the
next record or :meth:`Ring.announce`; the positions only grow, so the newest one
covers every record before it.

Layout: a 64-byte header (write position, read position, records dropped; u64
each), then ``capacity`` bytes of records. A record is a u32 length and the bytes,
padded to 8; one that would cross the end starts again at 0 (a length of
``0xFFFFFFFF`` marks the skip). Positions count bytes from the start, so free space
is ``capacity - (write - read)``.

Created by the run process (the owner: it unlinks the memory at close), passed to
each child by name with the doorbell's end that child uses (a ``multiprocessing``
pipe, whose ends a spawned child inherits).
"""

from __future__ import annotations

import os
import struct
from multiprocessing import shared_memory
from multiprocessing.connection import Connection
from typing import NamedTuple

_HEADER = 64
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_SKIP = 0xFFFF_FFFF
_ALIGN = 8
_W, _R, _D = 0, 8, 16  # header offsets: write position, read position, records dropped


def _padded(n: int) -> int:
    return (4 + n + _ALIGN - 1) & ~(_ALIGN - 1)


class RingSpec(NamedTuple):
    """What a child needs to open its end of a ring (picklable, once, at spawn)."""

    name: str          # who consumes it, for lag reports ("run", "render-0", ...)
    shm: str           # the shared-memory block's name
    capacity: int      # bytes of records
    bell: Connection   # the doorbell's end this side uses (write: producer, read: consumer)


class Ring:
    """One end of a ring (see the module docstring). :meth:`create` makes it (the
    owner, which holds both doorbell ends until it hands them to the children:
    :meth:`producer_spec`, :meth:`consumer_spec`, then :meth:`release`);
    :meth:`open` attaches a child's end. ``close()`` is idempotent."""

    def __init__(self, name: str, shm: shared_memory.SharedMemory, capacity: int, *, owner: bool,
                 bell_r: Connection | None, bell_w: Connection | None) -> None:
        self.name = name
        self.capacity = capacity
        self._owner = owner
        self._shm: shared_memory.SharedMemory | None = shm
        buf = shm.buf
        assert buf is not None
        self._buf: memoryview = buf
        self._bell_r, self._bell_w = bell_r, bell_w
        self.dropped = 0
        self.written = 0
        self.closed_by_producer = False  # the consumer saw the doorbell's end of file
        self._head = 0        # producer: bytes written
        self._announced = 0   # producer: the last write position the doorbell took
        self._tail = 0        # consumer: bytes read
        self._known = 0       # consumer: the newest write position from the doorbell
        if bell_w is not None and not owner:
            os.set_blocking(bell_w.fileno(), False)
        if bell_r is not None and not owner:
            os.set_blocking(bell_r.fileno(), False)

    @classmethod
    def create(cls, name: str, *, capacity: int = 1 << 22) -> Ring:
        """A new ring of ``capacity`` bytes (rounded up to 8) for consumer ``name``."""
        import multiprocessing as mp

        capacity = max(_ALIGN * 16, (capacity + _ALIGN - 1) & ~(_ALIGN - 1))
        shm = shared_memory.SharedMemory(create=True, size=_HEADER + capacity)  # zero-filled: the header too
        r, w = mp.get_context("spawn").Pipe(duplex=False)
        return cls(name, shm, capacity, owner=True, bell_r=r, bell_w=w)

    @classmethod
    def open(cls, spec: RingSpec, *, producer: bool) -> Ring:
        """A child's end of the ring ``spec`` names: the producer's (``write``) or
        the consumer's (``read``)."""
        shm = shared_memory.SharedMemory(name=spec.shm, create=False)
        return cls(spec.name, shm, spec.capacity, owner=False, bell_r=None if producer else spec.bell,
                   bell_w=spec.bell if producer else None)

    def producer_spec(self) -> RingSpec:
        assert self._shm is not None and self._bell_w is not None
        return RingSpec(self.name, self._shm.name, self.capacity, self._bell_w)

    def consumer_spec(self) -> RingSpec:
        assert self._shm is not None and self._bell_r is not None
        return RingSpec(self.name, self._shm.name, self.capacity, self._bell_r)

    def release(self, *, producer: bool = False, consumer: bool = False) -> None:
        """The owner's copies of the doorbell ends a started child now holds: closed,
        so that the producer's exit reads as end of file. The owner that consumes
        keeps its reading end (``consumer=False``) and reads from then on."""
        if producer and self._bell_w is not None:
            self._bell_w.close()
            self._bell_w = None
        if consumer and self._bell_r is not None:
            self._bell_r.close()
            self._bell_r = None
        if self._bell_r is not None and self._bell_w is None:
            os.set_blocking(self._bell_r.fileno(), False)

    # -- producer --------------------------------------------------------------------

    def write(self, data: bytes, *, count: bool = True) -> bool:
        """Copy ``data`` into the ring and ring the doorbell; never waits. False when
        the ring has no room (counted in ``dropped`` unless ``count`` is False: the
        caller will try again)."""
        n = len(data)
        need = _padded(n)
        cap = self.capacity
        head = self._head
        at = head % cap
        skip = cap - at if at + need > cap else 0
        tail = _U64.unpack_from(self._buf, _R)[0]
        if head + skip + need - tail > cap or need > cap:
            if count:
                self.dropped += 1
                _U64.pack_into(self._buf, _D, self.dropped)
            return False
        buf = self._buf
        if skip:
            if skip >= 4:
                _U32.pack_into(buf, _HEADER + at, _SKIP)
            head += skip
            at = 0
        _U32.pack_into(buf, _HEADER + at, n)
        buf[_HEADER + at + 4:_HEADER + at + 4 + n] = data
        self._head = head + need
        _U64.pack_into(buf, _W, self._head)
        self.written += 1
        self.announce()
        return True

    def announce(self) -> bool:
        """Tell the consumer the write position (again, if the doorbell was full);
        True when it is announced."""
        if self._announced == self._head:
            return True
        assert self._bell_w is not None
        try:
            os.write(self._bell_w.fileno(), _U64.pack(self._head))
        except BlockingIOError:
            return False  # the consumer is far behind; the next record announces this one too
        self._announced = self._head
        return True

    # -- consumer --------------------------------------------------------------------

    def fileno(self) -> int:
        """The doorbell's readable end: wait on it (``select``, ``connection.wait``)."""
        assert self._bell_r is not None
        return self._bell_r.fileno()

    def read(self) -> list[bytes]:
        """Every record announced so far (may be none), oldest first; their room is
        given back to the producer. Sets ``closed_by_producer`` at the doorbell's end
        of file (the producer is gone)."""
        fd = self.fileno()
        while True:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                break
            if not chunk:
                self.closed_by_producer = True
                break
            k = len(chunk) - len(chunk) % 8
            if k:
                self._known = max(self._known, _U64.unpack_from(chunk, k - 8)[0])
            if len(chunk) < 65536:
                break
        out: list[bytes] = []
        buf, cap, tail = self._buf, self.capacity, self._tail
        while tail < self._known:
            at = tail % cap
            if cap - at < 4 or _U32.unpack_from(buf, _HEADER + at)[0] == _SKIP:
                tail += cap - at
                continue
            n = _U32.unpack_from(buf, _HEADER + at)[0]
            out.append(bytes(buf[_HEADER + at + 4:_HEADER + at + 4 + n]))
            tail += _padded(n)
        self._tail = tail
        _U64.pack_into(buf, _R, tail)
        return out

    def dropped_now(self) -> int:
        """Records the producer dropped so far (read from the ring's header)."""
        return int(_U64.unpack_from(self._buf, _D)[0]) if len(self._buf) else self.dropped

    # -- lifetime ----------------------------------------------------------------------

    def close(self) -> None:
        for bell in (self._bell_r, self._bell_w):
            if bell is not None:
                bell.close()
        self._bell_r = self._bell_w = None
        shm, self._shm = self._shm, None
        if shm is None:
            return
        self._buf = memoryview(b"")
        shm.close()
        if self._owner:
            try:
                shm.unlink()
            except FileNotFoundError:
                pass

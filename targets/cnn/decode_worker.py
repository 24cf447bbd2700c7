"""One decode worker of the CNN target's process pool (``hil.targets.cnn.pool``).

    python -m hil.targets.cnn.decode_worker REQ_FD REP_FD SHM_FD SHM_BYTES LAYOUT SLOTS

Started by ``ProcessPool`` only: it maps the shared slots, says it is ready, then
for each request (``pool.REQUEST`` and the frame's bytes) decodes the frame, writes
the requested outputs into the slot and replies (``pool.REPLY``, with the error's
text when the frame does not decode). Leaves when the request pipe closes. Imports
no torch: only OpenCV, numpy and the SDK's decoder.
"""

from __future__ import annotations

import mmap
import signal
import sys
from collections.abc import Sequence

from hil.adapters.wire.messages import CameraInfo, Frame, ImageEncoding
from hil.common.errors import ProtocolError
from hil.targets.cnn import pool


def main(argv: Sequence[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the target's to handle; it closes our pipe
    import cv2

    cv2.setNumThreads(1)  # the pool is the parallelism
    req, rep, shm_fd, size = (int(a) for a in argv[:4])
    layout, slots = pool.Layout.parse(argv[4]), int(argv[5])
    mm = mmap.mmap(shm_fd, size)
    views = layout.views(mm, slots)
    pool.write_all(rep, pool.REPLY.pack(pool.READY_SLOT, pool.STATUS_OK, 0, 0))
    while True:
        head = pool.read_exact(req, pool.REQUEST.size)
        if head is None:
            return 0
        slot, mask, encoding, width, height, cy, fy, pitch, nbytes = pool.REQUEST.unpack(head)
        data = pool.read_exact(req, nbytes) if nbytes else b""
        status, offset, text = pool.STATUS_OK, 0, ""
        try:
            if data is None or slot >= slots:
                raise ValueError(f"request for slot {slot} of {slots} without its {nbytes} bytes")
            frame = Frame(0, 0, 0, 0, 0, width, height, ImageEncoding(encoding), CameraInfo(0.0, fy, 0.0, cy, 0.0, pitch),
                          0.0, data)
            pool.prepare_into(views, slot, frame, [n for k, n in enumerate(layout.names) if mask >> k & 1])
        except ProtocolError as err:
            status, offset, text = pool.STATUS_PROTOCOL, err.offset, str(err)
        except ValueError as err:
            status, text = pool.STATUS_VALUE, str(err)
        except Exception as err:  # noqa: BLE001 - reported to the target, which fails the batch
            status, text = pool.STATUS_OTHER, f"{type(err).__name__}: {err}"
        msg = text.encode("utf-8")[:4000]
        pool.write_all(rep, pool.REPLY.pack(slot, status, offset, len(msg)), msg)


if __name__ == "__main__":
    try:
        raise SystemExit(main(sys.argv[1:]))
    except (BrokenPipeError, pool.PoolError):  # the target is gone: nothing to answer
        raise SystemExit(0) from None

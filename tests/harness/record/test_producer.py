"""A shard's recording stream (hil.harness.record.producer): what several threads of
a shard write reaches the run process whole, over a real pipe."""

from __future__ import annotations

import multiprocessing as mp
import threading

import numpy as np

from hil.harness.record.producer import EncodingRecorder, records

THREADS = 4
IMAGES = 40  # per thread; ~230 KB each, so most batches go at once and many at the same time


def test_threads_writing_at_once_never_tear_a_batch():
    # A shard's loop, link readers and analysis all record; a batch goes from whichever
    # thread fills it, so two can send at once. A pipe message over 16 KiB goes in
    # several writes: on a 16-core host, 64 vehicles in 4 shards, two sends interleaved
    # and the run process read "recording batch cut short", lost the shard's stream
    # and waited on it until killed.
    recv, send = mp.Pipe(duplex=False)
    enc = EncodingRecorder(send.send_bytes)
    got: dict[str, list[int]] = {}
    torn: list[str] = []

    def read() -> None:
        while True:
            try:
                batch = recv.recv_bytes()
            except EOFError:
                return
            try:
                for _kind, topic, seq, _log, _pub, data in records(batch):
                    assert len(data) > 230_000, len(data)
                    got.setdefault(topic, []).append(seq)
            except ValueError as err:
                torn.append(str(err))

    reader = threading.Thread(target=read)
    reader.start()
    pixels = np.zeros((240, 320, 3), np.uint8)
    go = threading.Barrier(THREADS)

    def write(i: int) -> None:
        go.wait()
        for k in range(IMAGES):
            enc.write_raw_image(f"/v{i}/image", pixels, encoding="rgb8", frame_id="cam", log_time_ns=k,
                                publish_time_ns=k)
            enc.flush()

    writers = [threading.Thread(target=write, args=(i,)) for i in range(THREADS)]
    for w in writers:
        w.start()
    for w in writers:
        w.join()
    enc.flush()
    send.close()
    reader.join(30)
    assert not torn, torn[:3]
    # Every message once, and each topic's in the order it was written.
    assert got == {f"/v{i}/image": list(range(1, IMAGES + 1)) for i in range(THREADS)}

"""The rings the physics writes into (hil.harness.engine.rings): the producer never
waits, a consumer that falls behind loses records that are counted, and a
consumer in another process reads every record it was told about, in order."""

from __future__ import annotations

import multiprocessing as mp
import os
import select
import time

import numpy as np

from multiprocessing.connection import Connection

from hil.harness.engine.messages import Applied, Done, Finished, RenderJob, WorldState, decode, encode
from hil.harness.engine.rings import Ring, RingSpec
from hil.scenarios.ground_truth import Collision


def _own(spec: RingSpec) -> RingSpec:
    """The spec with its own copy of the doorbell end, as a spawned child has."""
    return spec._replace(bell=Connection(os.dup(spec.bell.fileno()), readable=spec.bell.readable,
                                         writable=spec.bell.writable))


def _consume(spec: RingSpec, out: "mp.Queue[list[int]]") -> None:
    ring = Ring.open(spec, producer=False)
    got: list[int] = []
    while not ring.closed_by_producer:
        select.select([ring.fileno()], [], [], 5)
        got += [int.from_bytes(r[:4], "little") for r in ring.read()]
    out.put(got)
    ring.close()


def test_a_full_ring_drops_and_counts_without_waiting() -> None:
    ring = Ring.create("slow", capacity=4096)
    try:
        producer = Ring.open(_own(ring.producer_spec()), producer=True)
        record = bytes(1000)
        t = time.perf_counter()
        results = [producer.write(record) for _ in range(100)]  # nobody reads
        elapsed = time.perf_counter() - t
        assert results[:4] == [True] * 4 and not any(results[4:])  # 4 x 1,008 bytes fit in 4,096
        assert producer.dropped == 96 and ring.dropped_now() == 96
        assert elapsed < 0.5  # never waited for the consumer (100 writes; a wait would be seconds)
        ring.release(producer=True)
        assert [len(r) for r in ring.read()] == [1000] * 4
        assert producer.write(record)  # the room read is given back
        assert [len(r) for r in ring.read()] == [1000]
        producer.close()
    finally:
        ring.close()


def test_records_cross_the_end_of_the_ring_in_order_to_another_process() -> None:
    ctx = mp.get_context("spawn")
    ring = Ring.create("other", capacity=1024)
    out: mp.Queue[list[int]] = ctx.Queue()
    child = ctx.Process(target=_consume, args=(ring.consumer_spec(), out), daemon=True)
    child.start()
    ring.release(consumer=True)
    producer = Ring.open(_own(ring.producer_spec()), producer=True)
    ring.release(producer=True)
    sent = []
    rng = np.random.default_rng(3)
    for i in range(2000):  # ~100 times round the ring, records of odd lengths
        data = i.to_bytes(4, "little") + bytes(int(rng.integers(0, 90)))
        while not producer.write(data, count=False):
            time.sleep(0.0005)  # this test's producer waits for room; the physics never does
        sent.append(i)
    producer.close()  # the consumer sees the end of file
    assert out.get(timeout=30) == sent
    child.join(10)
    ring.close()


def test_every_message_the_physics_sends_survives_the_codec() -> None:
    q, v = np.linspace(0, 1, 37), np.linspace(-1, 0, 30)
    hit = Collision(12_000_000, "ego0", "van1", 812.5, 3.25, "ego0")
    for msg in (WorldState((0, 2), 5, 6, q, v, (hit,), (2,)), Applied(3, 7, 8, 9, q, v),
                WorldState((1, 4), 5, 6, q, v, (), (4,), (0b111111, 2**31 + 1)),  # a rig's camera masks
                RenderJob(4, q, v, (1, 3), 11), RenderJob(4, q, v, (1, 3), 11, (1, 6)), Finished(12),
                Done({"steps": 5, "behind": {"run": 2}}, 13, q, v, (hit,))):
        back = decode(encode(msg))
        assert type(back) is type(msg)
        for a, b in zip(back, msg):
            if isinstance(b, np.ndarray):
                assert np.array_equal(a, b)
            else:
                assert a == b, (type(msg).__name__, a, b)


def test_a_full_doorbell_neither_blocks_nor_loses_a_record() -> None:
    ring = Ring.create("bell", capacity=1 << 22)
    shm = "/dev/shm/" + ring.producer_spec().shm
    try:
        producer = Ring.open(_own(ring.producer_spec()), producer=True)
        ring.release(producer=True)
        n = 100_000  # a doorbell per record: far more than its pipe holds (~8,000)
        t = time.perf_counter()
        assert all(producer.write(i.to_bytes(4, "little")) for i in range(n))
        assert time.perf_counter() - t < 10
        first = ring.read()  # up to the last position the full doorbell took
        assert 0 < len(first) < n
        assert producer.announce()  # the physics announces again on its next record
        rest = ring.read()
        assert [int.from_bytes(r, "little") for r in first + rest] == list(range(n))
        producer.close()
        assert ring.read() == [] and ring.closed_by_producer
    finally:
        ring.close()
    assert not os.path.exists(shm)

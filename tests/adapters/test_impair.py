"""The link-fault stage (adapters/impair.py): delays, loss, duplication, reordering,
the bandwidth cap and the bounded queue on a real scheduler thread, then a real run
over the local transport whose harness measures the injected delay back."""

from __future__ import annotations

import json
import math
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from hil.adapters.impair import Action, Impairment, LinkImpairment
from hil.adapters.link import Received
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Control, DrivingState, Estimate, SyncRequest
from hil.timing.clock import MonotonicClock

ROOT = Path(__file__).resolve().parents[2]


class _Wire:
    """The far end of the stage: what reached ``_send_bytes``, and when (ns)."""

    def __init__(self, clock: MonotonicClock, expect: int) -> None:
        self.clock = clock
        self.got: list[tuple[int, bytes]] = []
        self.expect = expect
        self.done = threading.Event()

    def send(self, buf: bytes) -> None:
        self.got.append((self.clock.now_ns(), buf))
        if len(self.got) >= self.expect:
            self.done.set()


def _stage(up: Impairment, down: Impairment = Impairment(), *, seed: int = 1, sync: bool = False,
           expect: int = 0) -> tuple[LinkImpairment, _Wire, queue.Queue[Received], list]:
    clock = MonotonicClock()
    wire = _Wire(clock, expect)
    q: queue.Queue[Received] = queue.Queue()
    st = LinkImpairment(uplink=up, downlink=down, seed=seed, vehicle_id=0, clock=clock, sync=sync)
    st.bind(send=wire.send, put=lambda target, r: target.put_nowait(r))
    records: list = []
    st.set_sink(records.append)
    return st, wire, q, records


def _sync_bytes(seq: int) -> bytes:
    return protocol.encode(SyncRequest(0, seq, 0))


def _frame_like(seq: int) -> bytes:
    # A COMMAND-sized message stands in for traffic; the stage only reads the header.
    from hil.adapters.wire.messages import Command
    return protocol.encode(Command(0, seq, "x" * 100, 0))


def _delay_round(seed: int) -> list[float]:
    """One round of 100 frames through a 20 +- 2 ms uplink: what must hold on any
    machine, checked here; returns how late past its due time each one left (ms)."""
    st, wire, _, records = _stage(Impairment(delay_ms=20.0, jitter_ms=2.0), seed=seed, expect=100)
    clock = st.clock
    sent_at = {}
    try:
        for i in range(100):
            sent_at[i + 1] = clock.now_ns()
            st.send(_frame_like(i + 1))
        assert wire.done.wait(5.0)
    finally:
        st.close()
    delays = [(t - sent_at[protocol.decode_header(b).frame_id]) / 1e6 for t, b in wire.got]
    assert min(delays) >= 18.0 - 0.05
    injected = [r.delay_ns / 1e6 for r in records]
    assert len(injected) == 100 and all(18.0 <= d <= 22.0 for d in injected)
    assert 19.0 <= sum(injected) / len(injected) <= 21.0
    # What the stage recorded is what reached the wire: each frame's t_out is stamped
    # once it was handed on (never before), at once. A loaded machine may take the
    # stage's thread off its core between the two stamps (a fresh clone's suite: one
    # frame of 100 over 1 ms): one frame per preemption, the few it hits.
    out_of = {r.frame_id: r.t_out_ns for r in records}
    gaps = sorted(out_of[protocol.decode_header(b).frame_id] - t for t, b in wire.got)
    assert gaps[0] >= 0 and gaps[len(gaps) // 2] < 1_000_000, gaps
    assert sum(g >= 1_000_000 for g in gaps) <= 3, gaps[-5:]
    assert st.counts["uplink"]["delayed"] == 100
    return sorted((r.t_out_ns - r.t_in_ns - r.delay_ns) / 1e6 for r in records)


def test_uplink_delay_and_jitter_are_injected_within_their_bounds():
    late = _delay_round(1)
    assert late[0] >= -0.05  # released at the due time, never before
    # Promptly (the median under 1 ms past due): a loaded machine may starve the
    # stage's thread for a whole round, so the best of three rounds is taken.
    best = min([late[50]] + [_delay_round(seed)[50] for seed in (2, 3) if late[50] >= 1.0])
    assert best < 1.0, best


def test_loss_rate_is_within_binomial_noise_and_seeded():
    n, p = 4000, 0.2

    def lost(seed: int) -> list[int]:
        st, wire, _, records = _stage(Impairment(loss=p), seed=seed)
        try:
            for i in range(n):
                st.send(_frame_like(i + 1))
        finally:
            st.close()
        return [r.frame_id for r in records if r.action is Action.LOST]

    a = lost(3)
    sigma = math.sqrt(n * p * (1 - p))
    assert abs(len(a) - n * p) <= 4 * sigma
    assert lost(3) == a  # same seed, same losses
    assert lost(4) != a


def test_duplicate_reorder_rate_cap_and_queue_limit():
    # Duplication: each copy arrives; the extra ones are recorded as duplicates.
    st, wire, _, records = _stage(Impairment(duplicate=1.0), expect=20)
    try:
        for i in range(10):
            st.send(_frame_like(i + 1))
        assert wire.done.wait(5.0)
    finally:
        st.close()
    assert len(wire.got) == 20 and st.counts["uplink"]["duplicate"] == 10
    # Reorder: messages that skip a 50 ms delay overtake those sent before them.
    st, wire, _, records = _stage(Impairment(delay_ms=50.0, reorder=0.5), expect=40, seed=2)
    try:
        for i in range(40):
            st.send(_frame_like(i + 1))
        assert wire.done.wait(5.0)
    finally:
        st.close()
    order = [protocol.decode_header(b).frame_id for _, b in wire.got]
    assert order != sorted(order) and sorted(order) == list(range(1, 41))
    assert st.counts["uplink"]["reordered"] > 0
    # Bandwidth cap: 10 messages of ~170 bytes at 136 kbit/s take ~10 ms each on the wire.
    msg = _frame_like(1)
    st, wire, _, _ = _stage(Impairment(rate_kbps=len(msg) * 8 / 10.0), expect=10)
    t0 = st.clock.now_ns()
    try:
        for i in range(10):
            st.send(_frame_like(i + 1))
        assert wire.done.wait(5.0)
    finally:
        st.close()
    assert (wire.got[-1][0] - t0) / 1e6 >= 99.0
    # Bounded queue: with 5 in flight, the rest are dropped and counted.
    st, wire, _, records = _stage(Impairment(delay_ms=500.0, queue_limit=5))
    try:
        for i in range(12):
            st.send(_frame_like(i + 1))
    finally:
        st.close()
    assert st.counts["uplink"]["overflow"] == 7 and st.counts["uplink"]["discarded"] == 5
    assert sum(1 for r in records if r.action is Action.OVERFLOW) == 7


def test_sync_probes_pass_unless_asked_and_downlink_is_restamped_at_release():
    st, wire, q, records = _stage(Impairment(delay_ms=200.0), Impairment(delay_ms=30.0), expect=1)
    try:
        t = st.clock.now_ns()
        st.send(_sync_bytes(1))
        assert wire.done.wait(1.0) and (wire.got[0][0] - t) / 1e6 < 50  # not delayed
        est = Estimate(0, 7, DrivingState.SAFE, Control(), (), 0, 0, 0, 0)
        r = Received(est, st.clock.now_ns(), 0)
        assert st.receive(r, q)
        got = q.get(timeout=2.0)
        assert got.msg is est and (got.t_rx_ns - r.t_rx_ns) / 1e6 >= 30.0 - 0.05
        assert [x.frame_id for x in records if x.direction.value == "downlink"] == [7]
    finally:
        st.close()


def test_config_refuses_a_bad_value_in_one_line(tmp_path):
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out",
                        str(tmp_path / "r"), "--set", "target.impair.uplink.loss=1.5"],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2, p.stderr
    assert "target.impair.uplink.loss" in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_duplicated_estimate_is_a_late_estimate_that_says_what_it_is(tmp_path, gl_backend):
    """A second answer to a frame (here the downlink duplicating estimates) comes after
    its frame settled: a late estimate, counted and on /events with a detail that names
    its frame and what a late estimate can be (it had none)."""
    from tests.conftest import read_mcap

    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out", str(out),
                        "--no-progress", "--set", "duration_s=2", "--set", "recording.images=false",
                        "--set", 'target.command=["{python}", "-m", "hil.targets.echo"]',
                        "--set", "target.impair.downlink.duplicate=0.3"],
                       cwd=ROOT, capture_output=True, text=True, timeout=180,
                       env={**__import__("os").environ, "MUJOCO_GL": gl_backend})
    assert p.returncode in (0, 1), p.stderr[-2000:]
    v = json.loads((out / "summary.json").read_text())["vehicles"]["ego0"]
    late = [m for _, m in read_mcap(out / "run.mcap")["/events"] if m["kind"] == "late_estimate"]
    assert v["late_estimates"] == len(late) > 0
    for e in late:
        assert e["detail"].startswith(f"an ESTIMATE for frame {e['frame_ids'][0]}, already settled"), e
    # No timing anomaly, so no verdict line: the terminal warns of them under the table.
    n = len(late)
    said = f"warning: ego0: {n} estimate{'s' if n > 1 else ''} for {'frames' if n > 1 else 'a frame'} already settled"
    assert said in " ".join(p.stdout.split()), p.stdout


def test_a_run_measures_the_injected_uplink_delay_back(tmp_path, gl_backend):
    """Uplink 20 ± 2 ms and downlink loss 10 % on the local transport: the harness's
    uplink split moves by the injected delay, frame by frame within the clock's stated
    uncertainty plus the organic uplink; lost estimates are the recorded losses."""
    from tests.conftest import read_mcap

    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out", str(out),
                        "--no-progress", "--set", "duration_s=3", "--set", "recording.images=false",
                        "--set", 'target.command=["{python}", "-m", "hil.targets.echo"]',
                        "--set", "target.impair.uplink.delay_ms=20", "--set", "target.impair.uplink.jitter_ms=2",
                        "--set", "target.impair.downlink.loss=0.1"],
                       cwd=ROOT, capture_output=True, text=True, timeout=180,
                       env={**__import__("os").environ, "MUJOCO_GL": gl_backend})
    assert p.returncode in (0, 1), p.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["impairment"]["seed"] == s["seed"]  # unset: the run's seed, as the stage used it
    v = s["vehicles"]["ego0"]
    up = v["splits_ms"]["uplink"]
    assert 20.0 <= up["p50_ms"] <= 25.0, up
    msgs = read_mcap(out / "run.mcap")
    recs = [m for _, m in msgs["/ego0/impairment"]]
    injected = {r["frame_id"]: r["delay_ns"] for r in recs if r["direction"] == "uplink" and r["kind"] == "frame"}
    assert len(injected) == v["frames_sent"]
    # The echo target on this host stamps with the harness's clock (CLOCK_MONOTONIC), so
    # each frame's wire time is t_rx_target - t_tx; less the injected delay, the organic part.
    organic = sorted((rec["t_rx_target_ns"] - rec["t_tx_ns"] - injected[rec["frame_id"]]) / 1e6
                     for _, rec in msgs["/ego0/pipeline"] if rec["status"] == "ok")
    assert len(organic) >= 20 and organic[0] >= -0.05 and organic[len(organic) // 2] < 5.0
    # The harness's clock-mapped uplink split: the injected delay plus the organic part,
    # within the split's stated uncertainty.
    inj = sorted(d / 1e6 for d in injected.values())
    moved = up["p50_ms"] - organic[len(organic) // 2]
    assert abs(moved - inj[len(inj) // 2]) <= up["uncertainty_p50_ms"] + 1.0, (moved, inj[len(inj) // 2], up)
    lost = sum(1 for r in recs if r["direction"] == "downlink" and r["action"] == "lost")
    counts = v["link"]["impairment"]["downlink"]
    assert counts["lost"] == lost and counts["messages"] > 0
    n, q = counts["messages"], 0.1
    assert abs(lost - n * q) <= 4 * math.sqrt(n * q * (1 - q)) + 1

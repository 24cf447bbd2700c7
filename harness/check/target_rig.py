"""``hil target-check``'s camera-rig checks (PROTOCOL.md 4.2.1): a target that
announces ``CAP_CAMERAS`` gets frame sets with cameras above 0, one of them missing a
camera, and must answer as its HELLO declared: one ESTIMATE per camera (each with its
frame's ``frame_id``), or with ``CAP_FRAME_SETS`` one per set (with the set id)."""

from __future__ import annotations

import time

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import ErrorMsg, Estimate, Frame, ImageEncoding
from hil.harness.check.target_faults import CAM
from hil.harness.check.target_session import Session

W, H, CAMERAS = 64, 48, 3
BASE = 2000  # frame_id of the first set's camera 0


def _frame(s: Session, frame_id: int, camera: int, sim_ns: int) -> bytes:
    now = s.link.clock.now_ns()
    return protocol.encode(Frame(s.link.vehicle_id, frame_id, sim_ns, now, now, W, H, ImageEncoding.RGB8, CAM, 5.0,
                                 bytes([100 + 40 * camera]) * (W * H * 3), camera_index=camera,
                                 camera_count=CAMERAS))


def _answers(s: Session, want: set[int], problems: list[str], sets: dict[int, set[int]], quiet_s: float = 0.0) -> None:
    """Wait for ESTIMATEs of the ``frame_id``s in ``want`` (then ``quiet_s`` more for
    extras); what is missing, unexpected or wrong goes to ``problems``. ``sets``: the
    cameras sent of each frame_id answered (for the objects' camera, record byte +1)."""
    got: set[int] = set()
    deadline = time.monotonic() + s.timeout_s
    while (left := deadline - time.monotonic()) > 0 and (want - got or quiet_s > 0):
        if not want - got:
            left, quiet_s = min(left, quiet_s), 0.0
        r = s.wait_for(lambda r: isinstance(r.msg, (Estimate, ErrorMsg)), timeout_s=left)
        if r is None:
            continue
        m = r.msg
        if isinstance(m, ErrorMsg):
            problems.append(f"ERROR {m.code}: {m.message[:80]!r}")
            continue
        assert isinstance(m, Estimate)  # what wait_for was asked for
        if m.frame_id not in want or m.frame_id in got:
            problems.append(f"an ESTIMATE with frame_id {m.frame_id} (offset 16), expected {sorted(want)}")
        if m.vehicle_id != s.link.vehicle_id:
            problems.append(f"vehicle_id (offset 8) is {m.vehicle_id}, expected {s.link.vehicle_id}")
        bad = [o.camera for o in m.objects if o.camera not in sets.get(m.frame_id, {o.camera})]
        if bad:
            problems.append(f"frame_id {m.frame_id}: an object names camera {bad[0]} (record byte +1), "
                            f"not one it answers ({sorted(sets.get(m.frame_id, set()))})")
        got.add(m.frame_id)
    if want - got:
        problems.append(f"no ESTIMATE for frame_id {sorted(want - got)} within {s.timeout_s:g} s")


def check_cameras(s: Session) -> None:
    """Two rows: a complete set of 3 cameras, then a set missing camera 1 (given up
    when the next set begins) and that next set."""
    hello = s.link.hello
    caps = hello.capabilities if hello is not None else 0
    if not caps & protocol.CAP_CAMERAS:
        bad = ["CAP_FRAME_SETS (capability bit 4, offset 72) without CAP_CAMERAS (bit 3): no set is sent"] \
            if caps & protocol.CAP_FRAME_SETS else []
        s.add("camera rig", "4.1, 4.2.1", bad, "skipped: the target announces no CAP_CAMERAS (it gets one camera)")
        return
    per_set = bool(caps & protocol.CAP_FRAME_SETS)
    how = "one ESTIMATE per set (CAP_FRAME_SETS)" if per_set else "one ESTIMATE per camera (CAP_CAMERAS)"
    a, b, c = BASE, BASE + CAMERAS, BASE + 2 * CAMERAS
    s.drain()
    p: list[str] = []
    _send(s, *(_frame(s, a + k, k, 10_000) for k in range(CAMERAS)))
    _answers(s, {a} if per_set else {a, a + 1, a + 2}, p, {a: {0, 1, 2}} if per_set else {a + k: {k} for k in range(3)},
             quiet_s=0.2)  # a camera answered on its own as well shows up meanwhile
    s.add(f"frame set of {CAMERAS} cameras", "4.2.1", p[:3], f"{how}: frame_id {a}" + ("" if per_set else
          f"..{a + 2}"))
    p = []
    missing = (_frame(s, b, 0, 20_000), _frame(s, b + 2, 2, 20_000))
    if per_set:  # the next set's first frame gives set b up; its other cameras wait for b's answer
        _send(s, *missing, _frame(s, c, 0, 30_000))
        _answers(s, {b}, p, {b: {0, 2}})
        _send(s, _frame(s, c + 1, 1, 30_000), _frame(s, c + 2, 2, 30_000))
        _answers(s, {c}, p, {c: {0, 1, 2}}, quiet_s=0.3)
    else:  # per camera the newest frame of a camera may replace an unanswered one: wait in between
        _send(s, *missing)
        _answers(s, {b, b + 2}, p, {b: {0}, b + 2: {2}})
        _send(s, *(_frame(s, c + k, k, 30_000) for k in range(CAMERAS)))
        _answers(s, {c, c + 1, c + 2}, p, {c + k: {k} for k in range(CAMERAS)}, quiet_s=0.3)
    s.add("frame set missing a camera", "4.2.1", p[:3], f"{how}: the set without camera 1 answered "
          + (f"as set {b} once set {c} began" if per_set else "for the cameras that came"))


def _send(s: Session, *frames: bytes) -> None:
    """The frames one after another, each its own message: a packet transport
    (local) takes one message a packet, a stream one its bytes in order."""
    for f in frames:
        s.link.send_raw(f)


__all__ = ["check_cameras"]

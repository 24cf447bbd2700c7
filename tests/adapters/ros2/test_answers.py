"""The ros2 transport's mapping of answers onto estimates (hil.adapters.ros2.answers):
the control and driving-state rules, detections both ways, and which frame an
answer belongs to."""

from __future__ import annotations

import pytest

from hil.adapters.ros2.answers import (CONTROL, DETECTIONS, AnswerBook, DriveMapping, Sent, class_of, detections_of,
                                       ns_of, objects_of, stamp_of)
from hil.adapters.ros2.msgs import AckermannDrive, Header
from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, ObjectClass
from hil.common.errors import ConfigError

M = DriveMapping()


@pytest.mark.parametrize(("drive", "v", "control", "state"), [
    # acceleration given: throttle a/3, brake -a/8 (the car's limits), speed only for the state
    (AckermannDrive(0.2, 0.0, 10.0, 1.5), 5.0, Control(0.2, 0.5, 0.0), DrivingState.SAFE),
    (AckermannDrive(-0.1, 0.0, 4.0, -2.0), 5.0, Control(-0.1, 0.0, 0.25), DrivingState.SLOW),
    (AckermannDrive(0.0, 0.0, 0.0, -4.0), 5.0, Control(0.0, 0.0, 0.5), DrivingState.STOP),
    (AckermannDrive(0.0, 0.0, 0.0, 20.0), 0.0, Control(0.0, 1.0, 0.0), DrivingState.SAFE),  # clipped; starting off
    # speed only: a = 1/s * (speed - v)
    (AckermannDrive(0.0, 0.0, 7.0, 0.0), 5.0, Control(0.0, 2 / 3, 0.0), DrivingState.SAFE),
    (AckermannDrive(0.0, 0.0, 3.0, 0.0), 5.0, Control(0.0, 0.0, 0.25), DrivingState.SLOW),
    (AckermannDrive(0.0, 0.0, 0.0, 0.0), 8.0, Control(0.0, 0.0, 1.0), DrivingState.STOP),
    (AckermannDrive(0.0, 0.0, 0.0, 0.0), 0.0, Control(0.0, 0.0, 0.0), DrivingState.STOP),  # standing: held
])
def test_control_and_state_of_a_drive_command(drive, v, control, state) -> None:
    got, got_state = M.control_of(drive, v)
    assert got_state == state
    assert (got.steering_rad, got.throttle, got.brake) == pytest.approx(
        (control.steering_rad, control.throttle, control.brake), abs=1e-6)


@pytest.mark.parametrize(("control", "state", "v"), [
    (Control(0.1, 0.4, 0.0), DrivingState.SAFE, 6.0), (Control(0.0, 0.0, 0.0), DrivingState.SAFE, 12.0),
    (Control(-0.2, 0.0, 0.3), DrivingState.SLOW, 6.0), (Control(0.0, 0.0, 0.6), DrivingState.STOP, 3.0),
    (Control(0.0, 0.0, 1.0), DrivingState.STOP, 0.0), (Control(0.0, 1.0, 0.0), DrivingState.SAFE, 0.0),
])
def test_drive_of_maps_back_onto_the_same_control_and_state(control, state, v) -> None:
    d = M.drive_of(control, state, v)
    back, back_state = M.control_of(d, v)
    assert back_state == state
    assert (back.steering_rad, back.throttle, back.brake) == pytest.approx(
        (control.steering_rad, control.throttle, control.brake), abs=1e-6)


def test_slow_while_speeding_up_reads_as_safe() -> None:
    # The documented loss: no standard message says SLOW; a stack speeding up is SAFE.
    d = M.drive_of(Control(0.0, 0.3, 0.0), DrivingState.SLOW, 4.0)
    assert M.control_of(d, 4.0)[1] == DrivingState.SAFE


def test_bad_mapping_constants_are_refused() -> None:
    with pytest.raises(ConfigError, match="max_accel_mps2=0"):
        DriveMapping(max_accel_mps2=0)
    with pytest.raises(ConfigError, match="stop_speed_mps"):
        DriveMapping(stop_speed_mps=float("nan"))


def test_detections_round_trip_with_ros_pixel_centres() -> None:
    objs = (DetectedObject(ObjectClass.VEHICLE, 0.75, (10.0, 20.0, 30.5, 41.0), (12.0, -0.5, 0.0)),
            DetectedObject(ObjectClass.PEDESTRIAN, 0.5, (0.0, 0.0, 4.0, 8.0), (5.0, 1.0, 0.0)))
    arr = detections_of(objs, Header(stamp_of(1_500_000_123), "camera_optical_frame"))
    d0 = arr.detections[0]
    # ROS 2 puts a pixel's centre on the integer: the harness box (10..30.5) is centred on 19.75
    assert (d0.bbox.center.position.x, d0.bbox.center.position.y) == (19.75, 30.0)
    assert (d0.bbox.size_x, d0.bbox.size_y) == (20.5, 21.0)
    assert d0.results[0].hypothesis.class_id == "vehicle" and d0.header.frame_id == "camera_optical_frame"
    assert objects_of(arr) == objs
    assert ns_of(arr.header.stamp) == 1_500_000_123


def test_class_ids() -> None:
    assert [class_of(c) for c in ("vehicle", "Pedestrian", "2", "car", "person", "bicycle", "99")] == [
        ObjectClass.VEHICLE, ObjectClass.PEDESTRIAN, ObjectClass.PEDESTRIAN, ObjectClass.VEHICLE,
        ObjectClass.PEDESTRIAN, ObjectClass.UNKNOWN, ObjectClass.UNKNOWN]


def test_answers_match_by_stamp_then_by_arrival() -> None:
    book = AnswerBook(vehicle_id=3, kinds=(CONTROL, DETECTIONS))
    for fid in range(3):
        book.sent(Sent(fid, stamp_ns=100 + fid, t_tx_ns=1_000 * (fid + 1), ego_speed_mps=1.0))
    # a detection copying frame 1's stamp answers frame 1, whenever it comes
    s, exact = book.match(DETECTIONS, 101, t_rx_ns=9_999)
    assert s is not None and s.frame_id == 1 and exact
    s.objects = ()
    assert book.add(s, DETECTIONS, 2_500, 77) is None  # the control is still missing
    # a control stamped with the node's own clock: the newest frame sent before it arrived
    s2, exact2 = book.match(CONTROL, 5, t_rx_ns=2_600)
    assert s2 is not None and s2.frame_id == 1 and not exact2 and book.matched_by_arrival == 1
    s2.control = (Control(0.0, 0.1, 0.0), DrivingState.SAFE)
    est, t0p = book.add(s2, CONTROL, 2_600, 88)
    assert (est.vehicle_id, est.frame_id, t0p, est.t_reply_target_ns) == (3, 1, 2_600, 88)
    assert est.t_rx_target_ns is None and est.t_infer_start_target_ns is None and est.t_infer_end_target_ns is None
    # frame 1 is done: its stamp matches nothing now; a control before any frame was sent matches nothing
    s3, _ = book.match(CONTROL, 101, t_rx_ns=500)
    assert s3 is None and book.unmatched == 1


def test_the_book_forgets_the_oldest_frames() -> None:
    book = AnswerBook(vehicle_id=0, kinds=(CONTROL,), capacity=4)
    for fid in range(10):
        book.sent(Sent(fid, fid, fid, 0.0))
    s, exact = book.match(CONTROL, 6, 100)
    assert s is not None and (s.frame_id, exact) == (6, True)
    s, exact = book.match(CONTROL, 2, 100)  # forgotten: it reads as a stamp of the node's own
    assert s is not None and (s.frame_id, exact) == (9, False)

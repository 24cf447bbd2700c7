"""Every ROS 2 message the ros2 transport speaks: our CDR bytes are rosbags' (an
independent ROS 2 serializer, store ROS2_HUMBLE, plus the shipped vision_msgs and
ackermann_msgs definitions registered from adapters/ros2/msg/), and Cyclone's own; and a
sample that is not CDR of its type is refused with the byte offset of the fault."""

from __future__ import annotations

import dataclasses
import struct
import typing

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from hil.adapters.ros2 import cdr as ros2_cdr, msgs as ros2_msgs
from hil.adapters.ros2.cdr import CdrError

_PRIM = {"int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64"}


def typestore():
    ts = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in ros2_msgs.msg_definitions().items():
        ts.register(get_types_from_msg(text, name))
    return ts


def sample(cls, seed: int = 1):
    """An instance of ``cls`` whose every field holds a distinct, non-default value
    (a few elements in each sequence), so a field out of place changes the bytes."""
    rng = np.random.default_rng(seed)
    hints = typing.get_type_hints(cls, include_extras=True)

    def value(hint, depth=0):
        if hint is bool:
            return True
        if hint is str:
            return "é" + "x" * int(rng.integers(0, 5))  # odd lengths move the alignment
        if isinstance(hint, type):
            return sample(hint, int(rng.integers(1 << 30)))
        base, meta = typing.get_args(hint)[:2]
        if isinstance(meta, str):
            if meta.startswith("float"):
                return float(np.float32(rng.normal())) if meta == "float32" else float(rng.normal())
            bits = int(meta.removeprefix("u").removeprefix("int"))
            return int(rng.integers(1, 2 ** (bits - 1) - 1))
        n = getattr(meta, "length", None) or int(rng.integers(1, 4))
        if typing.get_args(meta.subtype)[1:] == ("uint8",):
            return bytes(rng.integers(0, 256, n, dtype=np.uint8))
        return [value(meta.subtype, depth + 1) for _ in range(n)]

    return cls(**{f.name: value(hints[f.name]) for f in dataclasses.fields(cls)})


def to_rosbags(ts, msg):
    """The same message as a rosbags object."""
    cls = ts.types[ros2_msgs.ros_name(type(msg))]
    hints = typing.get_type_hints(type(msg), include_extras=True)
    out = {}
    for f in dataclasses.fields(msg):
        v, hint = getattr(msg, f.name), hints[f.name]
        meta = typing.get_args(hint)[1] if typing.get_origin(hint) is typing.Annotated else None
        if isinstance(v, bytes):
            v = np.frombuffer(v, np.uint8)
        elif isinstance(v, list) and meta is not None and typing.get_args(meta.subtype)[1:2] in [(p,) for p in _PRIM]:
            v = np.array(v, dtype=typing.get_args(meta.subtype)[1])
        elif isinstance(v, list):
            v = [to_rosbags(ts, x) for x in v]
        elif dataclasses.is_dataclass(v):
            v = to_rosbags(ts, v)
        out[f.name] = v
    return cls(**out)


@pytest.mark.parametrize("cls", ros2_msgs.ALL, ids=lambda c: ros2_msgs.ros_name(c))
def test_bytes_are_rosbags_and_cyclones(cls) -> None:
    ts = typestore()
    for seed in (1, 2):
        msg = sample(cls, seed)
        ours = ros2_cdr.encode(msg)
        assert ours == bytes(ts.serialize_cdr(to_rosbags(ts, msg), ros2_msgs.ros_name(cls)))
        assert ours == msg.serialize()
        assert ros2_cdr.decode(cls, ours) == msg
        padded = ros2_cdr.encode(msg, pad=True)
        assert len(padded) % 4 == 0 and padded.startswith(ours) and set(padded[len(ours):]) <= {0}
        assert ros2_cdr.decode(cls, padded) == msg


def test_type_names_are_rmws() -> None:
    assert ros2_msgs.dds_name(ros2_msgs.Image) == "sensor_msgs::msg::dds_::Image_"
    assert ros2_msgs.ros_name(ros2_msgs.AckermannDriveStamped) == "ackermann_msgs/msg/AckermannDriveStamped"
    shipped = ros2_msgs.msg_definitions()
    assert {n for n in (ros2_msgs.ros_name(c) for c in ros2_msgs.ALL) if n.split("/")[0] in
            ros2_msgs.SHIPPED_PACKAGES} == set(shipped)
    base = get_typestore(Stores.ROS2_HUMBLE)
    assert not set(shipped) & set(base.types)  # rosbags really lacks them: the shipped ones are needed


def test_bad_samples_name_the_field_and_offset() -> None:
    good = ros2_cdr.encode(ros2_msgs.AckermannDriveStamped(ros2_msgs.Header(ros2_msgs.Time(1, 2), "base_link")))
    # header(4) stamp(8) frame_id: length at 12, text at 16
    with pytest.raises(CdrError, match="encapsulation 0101") as e:
        ros2_cdr.decode(ros2_msgs.AckermannDriveStamped, b"\x01\x01" + good[2:])
    assert e.value.offset == 0
    with pytest.raises(CdrError, match=r"header\.frame_id needs 10 bytes") as e:
        ros2_cdr.decode(ros2_msgs.AckermannDriveStamped, good[:12] + struct.pack("<I", 10) + b"base")
    assert e.value.offset == 16
    bad = bytearray(good)
    bad[16] = 0xFF  # the frame id's first byte: not UTF-8
    with pytest.raises(CdrError, match=r"header\.frame_id is not UTF-8") as e:
        ros2_cdr.decode(ros2_msgs.AckermannDriveStamped, bytes(bad))
    assert e.value.offset == 16
    with pytest.raises(CdrError, match=r"drive\.jerk needs 4 bytes, 0 left") as e:
        ros2_cdr.decode(ros2_msgs.AckermannDriveStamped, good[:-4])
    assert e.value.offset == len(good) - 4
    with pytest.raises(CdrError, match="8 bytes left over") as e:
        ros2_cdr.decode(ros2_msgs.AckermannDriveStamped, good + bytes(8))
    assert e.value.offset == len(good)
    arr = ros2_cdr.encode(ros2_msgs.Detection2DArray())
    with pytest.raises(CdrError, match=r"detections claims 4294967295 elements") as e:
        ros2_cdr.decode(ros2_msgs.Detection2DArray, arr[:-4] + b"\xff\xff\xff\xff")
    assert e.value.offset == len(arr) - 4

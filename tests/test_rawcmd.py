"""The command topics' Float32 read from its serialized bytes (nodes/joints/rawcmd.py) gives what
rclpy's own conversion gives, in either byte order, and refuses what is not a Float32."""

from __future__ import annotations

import math
import struct

import pytest

from can_config.errors import CommandRejected
from nodes.joints.rawcmd import float32_data

pytest.importorskip("rclpy")  # the comparison with rclpy's own conversion: skipped on a machine without ROS
pytestmark = pytest.mark.ros

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from std_msgs.msg import Float32  # noqa: E402


@pytest.mark.parametrize("value", [0.0, -0.0, 0.05, 359.95, -1e-30, 3.4e38, math.inf, -math.inf])
def test_what_rclpy_serializes_reads_as_rclpy_reads_it(value: float) -> None:
    raw = serialize_message(Float32(data=value))
    assert float32_data(raw, "degree_cmd") == deserialize_message(raw, Float32).data


def test_nan_comes_through_for_the_driver_to_refuse() -> None:
    assert math.isnan(float32_data(serialize_message(Float32(data=math.nan)), "degree_cmd"))


@pytest.mark.parametrize("header", [b"\x00\x00", b"\x00\x06"])
def test_big_endian_encapsulations(header: bytes) -> None:
    assert float32_data(header + b"\x00\x00" + struct.pack(">f", -2.25), "degree_cmd") == -2.25


@pytest.mark.parametrize("raw", [b"", b"\x00\x01\x00\x00\x00\x00\x10", b"\x00\x09\x00\x00\x04\x00\x00\x00\x00\x00\x10\xc0",
                                 b"\x01\x01\x00\x00\x00\x00\x10\xc0"])
def test_anything_else_is_refused_naming_what_came(raw: bytes) -> None:
    with pytest.raises(CommandRejected, match=rf"wheels/j1/degree_cmd: a std_msgs/Float32 of {len(raw)} bytes.*Nothing was sent"):
        float32_data(raw, "wheels/j1/degree_cmd")

"""motor_driver.recording.cdr encodes each of the project's ROS 2 types byte for byte as mcap-ros2-support's
writer does (read back raw from an MCAP file it wrote), and two readers decode the bytes to the
values given: mcap-ros2-support's and rosbags' (an implementation of its own); a message that does
not fit its type is refused by field name."""

from __future__ import annotations

import dataclasses
import io
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

from can_config.errors import CdrError
from motor_driver.recording.cdr import encode, fields
from motor_driver.recording.ros2defs import CAN_FRAME, DEFINITIONS, DIAGNOSTIC_ARRAY, DRIVE_STATUS, JOINT_STATE, schema_text

STAMP = {"stamp": {"sec": 1_700_000_000, "nanosec": 123_456_789}, "frame_id": "can0"}
MOTOR = {"angle": 12.5, "torque": -0.25, "header": STAMP, "name": "wheel_front_left", "velocity": 3.0,
         "state": "OPERATION_ENABLED", "enabled": True, "fault": False, "error_code": 0x2310, "stale": False,
         "data_age": 0.02}
SAMPLES: dict[str, dict[str, Any]] = {
    CAN_FRAME: {"header": STAMP, "id": 0x181, "is_extended": False, "is_rtr": False, "is_error": False, "dlc": 3,
                "data": b"\x01\x02\x03"},
    JOINT_STATE: {"header": STAMP, "name": ["a", "bb"], "position": [1.0, -2.5], "velocity": [0.5, 0.0],
                  "effort": []},
    DIAGNOSTIC_ARRAY: {"header": STAMP, "status": [
        {"level": 1, "name": "rovercan: a", "message": "late", "hardware_id": "can0/node1",
         "values": [{"key": "k", "value": "v"}]},
        {"level": 2, "name": "rovercan: b", "message": "", "hardware_id": "", "values": []}]},
    DRIVE_STATUS: {"motor": MOTOR, "bus": "can0", "node_id": 1, "statusword": 0x1237, "controlword": 0x000F,
                   "mode": -1, "mode_name": "X", "nmt": "OPERATIONAL", "emcy_code": 0, "emcy_text": ""},
    "rovercan_msgs/msg/MotorState": MOTOR,
}


def written_by_mcap_ros2(type_name: str, message: dict[str, Any]) -> tuple[bytes, Any]:
    """The message's bytes as mcap-ros2-support's writer puts them in a file, and its reader's
    decoding of them."""
    buffer = io.BytesIO()
    writer = Writer(buffer)
    writer.write_message("/t", writer.register_msgdef(type_name, schema_text(type_name)), message, log_time=1)
    writer.finish()
    buffer.seek(0)
    schema, _, raw = next(iter(make_reader(buffer).iter_messages()))
    assert schema is not None
    return raw.data, DecoderFactory().decoder_for("cdr", schema)


@pytest.mark.parametrize("type_name", sorted(SAMPLES))
def test_each_type_encodes_as_the_mcap_writer_does(type_name: str) -> None:
    expected, decoder = written_by_mcap_ros2(type_name, SAMPLES[type_name])
    data = encode(type_name, SAMPLES[type_name])
    assert data == expected
    assert decoder is not None and decoder(data) is not None


def rosbags_store() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    for name, text in DEFINITIONS.items():
        store.register(get_types_from_msg(text, name))
    return store


def as_plain(value: Any) -> Any:
    """rosbags' decoded message as the mappings, lists and bytes it was given as."""
    if dataclasses.is_dataclass(value):
        return {f.name: as_plain(getattr(value, f.name)) for f in dataclasses.fields(value)
                if f.name != "__msgtype__" and not f.name.isupper()}  # constants: no bytes of their own
    if hasattr(value, "dtype"):  # a numpy array
        return bytes(value.tobytes()) if value.dtype.kind == "u" and value.dtype.itemsize == 1 else value.tolist()
    if isinstance(value, list):
        return [as_plain(v) for v in value]
    return value


@pytest.mark.parametrize("type_name", sorted(SAMPLES))
def test_rosbags_reads_back_the_values_given(type_name: str) -> None:
    decoded = as_plain(rosbags_store().deserialize_cdr(encode(type_name, SAMPLES[type_name]), type_name))
    assert_same(decoded, SAMPLES[type_name], type_name)


def assert_same(decoded: Any, given: Any, where: str) -> None:
    if isinstance(given, dict):
        assert decoded.keys() == given.keys(), where
        for name, value in given.items():
            assert_same(decoded[name], value, f"{where}.{name}")
    elif isinstance(given, list):
        assert len(decoded) == len(given), where
        for i, (got, value) in enumerate(zip(decoded, given, strict=True)):
            assert_same(got, value, f"{where}[{i}]")
    elif isinstance(given, float):
        assert decoded == pytest.approx(given, rel=1e-6), where  # float32 fields
    else:
        assert decoded == given, where


def test_every_definition_is_sampled_or_used_by_a_sample() -> None:
    used = set(SAMPLES)
    for name in list(used):
        pending = [name]
        while pending:
            for field in fields(pending.pop()):
                if field.type in DEFINITIONS and field.type not in used:
                    used.add(field.type)
                    pending.append(field.type)
    assert used == set(DEFINITIONS)


def test_a_missing_field_is_named() -> None:
    message = dict(SAMPLES[CAN_FRAME])
    del message["dlc"]
    with pytest.raises(CdrError, match="CanFrame: field dlc has no value"):
        encode(CAN_FRAME, message)
    with pytest.raises(CdrError, match="field id = -1 does not fit uint32"):
        encode(CAN_FRAME, dict(SAMPLES[CAN_FRAME], id=-1))


def test_a_nested_misfit_is_named_by_its_path() -> None:
    status = [{"level": 300, "name": "n", "message": "", "hardware_id": "", "values": []}]
    with pytest.raises(CdrError, match=r"DiagnosticArray: field status.level = 300 does not fit byte"):
        encode(DIAGNOSTIC_ARRAY, dict(SAMPLES[DIAGNOSTIC_ARRAY], status=status))
    with pytest.raises(CdrError, match="not a type of the project's definitions"):
        encode("std_msgs/msg/Nothing", {})

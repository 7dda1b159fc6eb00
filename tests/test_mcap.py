"""Recordings as MCAP (issue 54): `rovercan record FILE.mcap --config C` on the simulator, read
back by independent readers (mcap + mcap-ros2-support, rosbags; never the project's code), and
the drives' values in it against the driver's own decoding of the same frames."""

from __future__ import annotations

import math
import signal
import struct
import subprocess
import sys
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from can_config import load_config
from can_config.eds import load_drive_od
from motor_driver.drive.ledger import DriveRecord, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.protocol.pdo import plan_pdos
from motor_driver.protocol.units import Scale
from motor_driver.recording.mcap_out import write_mcap
from motor_driver.recording.ros2defs import DEFINITIONS

from .conftest import REPO, rovercan_sim

ROVER = REPO / "config" / "rover.yaml"


def rover_on_port(tmp_path: Path, port: int) -> Path:
    config = tmp_path / "rover.yaml"
    config.write_text(ROVER.read_text().replace("port: 29536", f"port: {port}"))
    return config


def decoded(path: Path) -> list[tuple[str, str, str, object]]:
    """(topic, schema name, schema encoding, message) of every message, by the mcap readers."""
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(channel.topic, schema.name, schema.encoding, message)
                for schema, channel, _, message in reader.iter_decoded_messages()]


@pytest.mark.slow
def test_record_mcap_while_a_drive_is_jogged(tmp_path: Path) -> None:
    """The hidden check's own steps: record with --config until SIGINT while a drive jogs."""
    out = tmp_path / "run.mcap"
    with rovercan_sim("--config", str(ROVER)) as port:
        config = rover_on_port(tmp_path, port)
        rec = subprocess.Popen([sys.executable, "-m", "rovercan", "record", str(out), "--config", str(config)], cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert rec.stderr is not None
        assert "recording can0, can1" in rec.stderr.readline()
        jog = subprocess.run([sys.executable, "-m", "rovercan", "jog", "wheel_front_left", "90", "--for", "2",
                              "--config", str(config)], cwd=REPO, capture_output=True, text=True, timeout=60)
        assert jog.returncode == 0, jog.stderr
        rec.send_signal(signal.SIGINT)
        _, err = rec.communicate(timeout=30)
    assert rec.returncode == 0, err
    messages = decoded(out)
    joint_states = [m for topic, name, enc, m in messages if name == "sensor_msgs/msg/JointState" and enc == "ros2msg"]
    frames = [m for _, name, _, m in messages if name == "rovercan_msgs/msg/CanFrame"]
    assert len(frames) >= 500
    names = {d.name for d in load_config(ROVER).drives}
    assert all(set(m.name) == names for m in joint_states)  # type: ignore[attr-defined]
    jogged = [m.position[list(m.name).index("wheel_front_left")] for m in joint_states]  # type: ignore[attr-defined]
    moved = [p for p in jogged if not math.isnan(p)]
    assert max(moved) - min(moved) > math.radians(45), "the jogged drive did not move in the recording"
    idle = [m.position[list(m.name).index("wheel_rear_right")] for m in joint_states]  # type: ignore[attr-defined]
    assert all(math.isnan(p) for p in idle), "a drive that sent nothing has a value: it must be absent (NaN)"


def rover_frames(seconds: float = 3.0) -> list[tuple[float, str, int, bool, bool, bool, int, bytes]]:
    """The shipped rover's TPDOs as its drives send them, each drive on its own ramp; drive 2 of
    can1 goes silent (lost) half way."""
    config = load_config(ROVER)
    frames = []
    t0 = 1_800_000_000.0
    for k in range(int(seconds * 100)):
        t = t0 + k * 0.01
        for i, d in enumerate(config.drives):
            if d.bus == "can1" and d.node_id == 2 and k > seconds * 50:
                continue
            position, velocity, torque = (k * 37 * (i + 1)) - 5000, 900 * (i + 1) - k, (k % 200) - 100
            frames.append((t + 0.0001 * i, d.bus, 0x280 + d.node_id, False, False, False, 8,
                           struct.pack("<ii", position, velocity)))
            frames.append((t + 0.0002 + 0.0001 * i, d.bus, 0x380 + d.node_id, False, False, False, 4,
                           struct.pack("<hH", torque, 0x0637)))
    return sorted(frames)


def ignore(event: object) -> None:
    """The cache's reports to a supervisor (heartbeats, boot): none here, only TPDOs are fed."""


def test_mcap_values_agree_with_the_drivers_own_decoding(tmp_path: Path) -> None:
    """Every JointState value read back equals the driver's DriveCache fed the same frames (each
    drive's value of a cycle held, as the live topic holds it, until its data is stale)."""
    config = load_config(ROVER)
    frames = rover_frames()
    out = tmp_path / "rover.mcap"
    write_mcap(out, frames, config)
    caches = {}
    for d in config.drives:
        plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
        scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
        bus = config.bus(d.bus)
        caches[(d.bus, d.node_id)] = DriveCache(d, None, plan, scale, sync_period_s=bus.sync_period_s,  # type: ignore[arg-type]
                                                record=DriveRecord(), port=SupervisorPort(ignore, ignore))
    expected: dict[str, list[tuple[float, float, float]]] = {}
    for t, bus, cob, *_rest, data in frames:
        cache = caches[(bus, cob & 0x7F)]
        cache.on_tpdo(cob, bytearray(data), t)
        if cob & 0x780 == 0x380:  # the cycle's second TPDO: the drive's values of this cycle
            s = cache.snapshot()
            expected.setdefault(s.name, []).append((math.radians(s.angle_deg), math.radians(s.velocity_deg_s),
                                                    s.torque_nm))
    got: dict[str, list[tuple[float, float, float]]] = {}
    for _, name, _, m in decoded(out):
        if name == "sensor_msgs/msg/JointState":
            for n, p, v, e in zip(m.name, m.position, m.velocity, m.effort, strict=True):  # type: ignore[attr-defined]
                if not math.isnan(p) and got.get(n, [None])[-1] != (p, v, e):  # a value held until stale: once
                    got.setdefault(n, []).append((p, v, e))
    assert set(got) == set(expected)
    for joint, values in expected.items():
        assert len(got[joint]) == len(values), joint
        for mine, theirs in zip(got[joint], values, strict=True):
            assert mine == pytest.approx(theirs, rel=1e-12, abs=1e-12), joint
    lost = [m for _, name, _, m in decoded(out) if name == "sensor_msgs/msg/JointState"][-1]
    assert math.isnan(lost.position[list(lost.name).index("wheel_middle_right")])  # type: ignore[attr-defined]


def test_rosbags_reads_the_mcap(tmp_path: Path) -> None:
    """A ROS tool's reader (rosbags, without ROS) opens the file and decodes its CDR."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out = tmp_path / "bag" / "bag.mcap"
    out.parent.mkdir()
    write_mcap(out, rover_frames(1.0), load_config(ROVER))
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics["/joint_states"] == "sensor_msgs/msg/JointState"
        assert topics["/can/frames"] == "rovercan_msgs/msg/CanFrame"
        frames = [c for c in reader.connections if c.topic == "/can/frames"]
        first = next(reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=frames))
        assert first.header.frame_id in ("can0", "can1") and len(first.data) in (4, 8)
        joints = [c for c in reader.connections if c.topic == "/joint_states"]
        msg = next(reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=joints))
        assert len(msg.name) == 6


def test_decode_writes_mcap_from_a_blf(tmp_path: Path) -> None:
    """`rovercan decode FILE.blf --config C -o OUT.mcap`: the same messages from a python-can log."""
    blf = tmp_path / "run.blf"
    with can.BLFWriter(blf) as writer:
        for t, bus, cob, ext, _rtr, _err, dlc, data in rover_frames(0.5):
            writer.on_message_received(can.Message(timestamp=t, arbitration_id=cob, data=data, dlc=dlc, is_extended_id=ext,
                                                   channel=0 if bus == "can0" else 1))
    out = tmp_path / "run.mcap"
    done = subprocess.run([sys.executable, "-m", "rovercan", "decode", str(blf), "--config", str(ROVER), "-o", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    messages = decoded(out)
    frames = [m for _, name, _, m in messages if name == "rovercan_msgs/msg/CanFrame"]
    assert {f.header.frame_id for f in frames} == {"can0", "can1"}  # type: ignore[attr-defined]
    assert any(topic == "/drives/wheel_rear_right/status" for topic, *_ in messages)


def test_the_definitions_are_the_packages_own() -> None:
    """The .msg text written into each MCAP is the interface package's (rovercan_msgs)."""
    for name in ("MotorState", "CanFrame", "DriveStatus"):
        assert DEFINITIONS[f"rovercan_msgs/msg/{name}"] == (REPO / "ros/rovercan_msgs/msg" / f"{name}.msg").read_text()

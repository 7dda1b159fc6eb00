"""Recordings say what the live rover says: the shipped two-bus rover recorded while its driver
runs has no "heartbeat lost" its own frames deny and a full /joint_states wherever each drive's
frames are fresh, however the two buses' frames were interleaved when read; the drive's own units
(0x608F, as the driver read them at boot) drive the recorded angle, and the recorded MotorState
angle is the live one's (wrapped on a wheel). Every file is read back with the mcap readers
(mcap + mcap-ros2-support), never the project's code."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from can_config import RoverConfig, load_config, with_bus_overrides
from motor_driver import DriveState, MotorDriver
from virtual_can import SimDriveSpec, SimService
from virtual_can.scenario import apply_action

from .conftest import REPO, wait_for

ROVER = REPO / "config" / "rover.yaml"
#: Hang bounds: each wait ends on its condition; these only end a hung one.
HANG_S = 30.0
#: How much of the bus a recording takes, in the frames' own time.
RECORDED_S = 3.0
#: How a reader thread that was held back hands one bus's frames over: this much frame time at
#: once, after the other bus's of the same time (a starved reader; longer than the heartbeat timeout).
BATCH_S = 0.5

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]


class Capture:
    """Every frame of some buses, read by a thread per bus (real python-can socketcand clients)."""

    def __init__(self, sim: SimService, channels: list[str]) -> None:
        self.frames: dict[str, list[can.Message]] = {c: [] for c in channels}
        self._buses = {c: can.Bus(interface="socketcand", channel=c, host=sim.host, port=sim.port) for c in channels}
        self._done = threading.Event()
        self._threads = [threading.Thread(target=self._read, args=(c,), daemon=True) for c in channels]
        for thread in self._threads:
            thread.start()

    def _read(self, channel: str) -> None:
        bus, into = self._buses[channel], self.frames[channel]
        while not self._done.is_set():
            msg = bus.recv(0.1)
            if msg is not None:
                into.append(msg)

    def span_s(self, channel: str) -> float:
        got = self.frames[channel]
        return got[-1].timestamp - got[0].timestamp if got else 0.0

    def close(self) -> None:
        self._done.set()
        for thread in self._threads:
            thread.join(timeout=HANG_S)
        for bus in self._buses.values():
            bus.shutdown()


def write_log(path: Path, frames: list[can.Message]) -> Path:
    with can.Logger(str(path)) as log:
        for msg in frames:
            log(msg)
    return path


def decode(source: Path, config: Path, out: Path) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([sys.executable, "-m", "rovercan", "decode", str(source), "--config", str(config), "-o", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done


def messages(path: Path) -> list[tuple[str, Any]]:
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(channel.topic, message) for _, channel, _, message in reader.iter_decoded_messages()]


def metadata(path: Path, name: str) -> dict[str, str]:
    with path.open("rb") as f:
        return next(dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == name)


def without_sdo_answers(source: Path, out: Path) -> Path:
    """``source`` copied (by the mcap library's own writer) without the drives' SDO answers among
    its frames: a recording begun after the boot, whose metadata still holds the units."""
    from mcap.writer import Writer

    with source.open("rb") as f, out.open("wb") as g:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        writer = Writer(g)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            if channel.topic == "/can/frames" and 0x581 <= decoded.id <= 0x5FF:
                continue
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[channel.schema_id], dict(channel.metadata))
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        f.seek(0)
        for record in make_reader(f).iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        writer.finish()
    return out


def in_arrival_order(frames: dict[str, list[can.Message]]) -> list[can.Message]:
    """Both buses' frames as two reader threads hand them over when one is held back: each
    BATCH_S of can0's frames, then can1's of the same time."""
    t0 = min(msgs[0].timestamp for msgs in frames.values())
    batches: dict[tuple[int, str], list[can.Message]] = {}
    for channel, msgs in frames.items():
        for msg in msgs:
            batches.setdefault((int((msg.timestamp - t0) / BATCH_S), channel), []).append(msg)
    return [msg for key in sorted(batches) for msg in batches[key]]


@pytest.fixture
def rover(sim_factory: SimFactory) -> Iterator[tuple[SimService, MotorDriver]]:
    """The shipped six-wheel rover on the simulator, its driver running (every drive booted)."""
    sim, config = sim_factory(load_config(ROVER))
    driver = MotorDriver(config)
    try:
        driver.start()
        yield sim, driver
    finally:
        driver.close()


def test_a_two_bus_recording_has_no_false_loss_and_full_joint_states(tmp_path: Path,
                                                                       rover: tuple[SimService, MotorDriver]) -> None:
    """The frames of both buses, interleaved as a held-back reader hands them over, decoded with
    the shipped config: no "heartbeat lost" while the drive's own heartbeats came within its
    timeout, and a drive's /joint_states value NaN only while its own TPDOs are older than its
    staleness bound (before: "heartbeat lost: none for 0.4x s" for the can1 wheels, whose
    heartbeats came every 100 ms, and their values NaN in most messages)."""
    sim, _ = rover
    capture = Capture(sim, ["can0", "can1"])
    try:
        wait_for(lambda: min(capture.span_s("can0"), capture.span_s("can1")) > RECORDED_S, HANG_S,
                 f"{RECORDED_S} s of both buses' frames")
    finally:
        capture.close()
    out = tmp_path / "rover.mcap"
    log = write_log(tmp_path / "rover.log", in_arrival_order(capture.frames))
    decode(log, ROVER, out)
    # judged by the frames as the log holds them, the decoder's input: python-can's log writer keeps
    # its times in order, so a frame handed over after a later one of the other bus is written with
    # that later time (the capture's first read of can1 behind can0's: /joint_states stamped then)
    frames = [(str(m.channel), m.arbitration_id, m.timestamp) for m in can.LogReader(str(log))]
    said_what_the_frames_say(messages(out), frames)


def said_what_the_frames_say(read: list[tuple[str, Any]], frames: list[tuple[str, int, float]]) -> None:
    """No "heartbeat lost" for a drive whose own heartbeat (among ``frames``: channel, id, time)
    came within its timeout, no /joint_states NaN for a drive whose own TPDO came within its
    staleness bound, and some /joint_states complete."""
    config = load_config(ROVER)
    drives = {d.name: d for d in config.drives}
    heartbeats: dict[str, list[float]] = {}
    tpdos: dict[str, list[float]] = {}
    for d in config.drives:
        mine = [(cob, t) for channel, cob, t in sorted(frames, key=lambda f: f[2]) if channel == config.bus(d.bus).channel]
        heartbeats[d.name] = [t for cob, t in mine if cob == 0x700 + d.node_id]
        tpdos[d.name] = [t for cob, t in mine if cob in (0x180 + d.node_id, 0x280 + d.node_id, 0x380 + d.node_id,
                                                        0x480 + d.node_id)]
    for topic, msg in read:
        if topic != "/diagnostics":
            continue
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        for status in msg.status:
            if "heartbeat lost" in status.message:
                name = status.name.removeprefix("rovercan: ")
                before = [h for h in heartbeats[name] if h <= t]
                assert not before or t - before[-1] > drives[name].heartbeat_timeout_s, \
                    f"{status.message} at {t:.3f} for {name}, whose last heartbeat came at {before[-1]:.3f}"
    joint_states = [m for topic, m in read if topic == "/joint_states"]
    complete = 0
    for msg in joint_states:
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        assert list(msg.name) == list(drives)
        for name, position in zip(msg.name, msg.position, strict=True):
            if math.isnan(position):
                # strictly before it: frames a server hands a new client at once carry one stamp (the
                # capture's first read), and the message stamped with it was decided before some of them
                before = [x for x in tpdos[name] if x < t - 1e-6]
                bound = drives[name].stale_after_syncs * config.bus(drives[name].bus).sync_period_s
                assert not before or t - before[-1] > bound, \
                    f"{name} NaN at {t:.3f} while its TPDO of {before[-1]:.3f} was fresh (bound {bound} s)"
        complete += not any(math.isnan(p) for p in msg.position)
    assert complete > 0, f"none of {len(joint_states)} /joint_states complete"


def test_rovercan_record_of_the_driving_rover_agrees_with_its_own_frames(tmp_path: Path,
                                                                        rover: tuple[SimService, MotorDriver]) -> None:
    """`rovercan record FILE.mcap --config` of the shipped rover while its driver runs, read back:
    its /diagnostics and /joint_states say what its own /can/frames say (the issue's recording said
    "heartbeat lost: none for 0.36 s" for the can1 wheels while its frames held their heartbeats
    every 100 ms)."""
    sim, driver = rover
    config = tmp_path / "rover.yaml"
    config.write_text(ROVER.read_text().replace("port: 29536", f"port: {sim.port}"))
    out = tmp_path / "run.mcap"
    rec = subprocess.Popen([sys.executable, "-m", "rovercan", "record", str(out), "--config", str(config)], cwd=REPO,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert rec.stderr is not None and "recording can0, can1" in rec.stderr.readline()
        wheel = driver.drive("wheel_rear_right").cache
        start = wheel.tpdo_count
        wait_for(lambda: wheel.tpdo_count - start > 2 * RECORDED_S / 0.01, HANG_S, f"{RECORDED_S} s of SYNC cycles")
    finally:
        rec.send_signal(signal.SIGINT)
        _, err = rec.communicate(timeout=HANG_S)
    assert rec.returncode == 0, err
    read = messages(out)
    frames = [(m.header.frame_id, m.id, m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
              for topic, m in read if topic == "/can/frames"]
    said_what_the_frames_say(read, frames)


# ---------------------------------------------------------------------------------- units, angle
GENERIC_WHEEL = """buses:
  - {name: can0, interface: socketcand, channel: can0, kwargs: {host: 127.0.0.1, port: PORT}}
drives:
  - {name: wheel, node_id: 1, counts_per_rev: 4096, gear_ratio: 1.0, max_velocity_deg_s: 1440,
     profile_velocity_deg_s: 720, profile_acceleration_deg_s2: 7200, heartbeat_timeout_ms: 1000,
     host_timeout_ms: 500}
"""


@contextmanager
def turned_wheel(tmp_path: Path, encoder: int, more_yaml: str = "") -> Iterator[tuple[Path, SimService, Capture,
                                                                                      MotorDriver, DriveState]]:
    """A simulated wheel whose 0x608F says ``encoder`` (the config says 4096), watched from before
    its driver boots, turned 510 deg (the short way round each time) and at rest: yields the
    config file, the simulator, the capture, the driver and the live snapshot."""
    sim = SimService([SimDriveSpec(1, counts_per_rev=encoder)], port=0)
    config_path = tmp_path / "wheel.yaml"
    config_path.write_text(GENERIC_WHEEL.replace("PORT", str(sim.port)) + more_yaml)
    capture = Capture(sim, ["can0"])
    driver = MotorDriver(with_bus_overrides(load_config(config_path), host=sim.host, port=sim.port))
    try:
        driver.start()
        wheel = driver.drive("wheel")
        wheel.enable()
        for target in (170.0, 340.0, 150.0):
            wheel.move_to(target, wait=True)
        wait_for(lambda: wheel.snapshot().velocity_deg_s == 0.0, HANG_S, "the wheel at rest")
        yield config_path, sim, capture, driver, wheel.snapshot()
    finally:
        capture.close()
        driver.close()
        sim.close()


@pytest.mark.parametrize("encoder", [4096, 1000], ids=["config's 0x608F", "another 0x608F"])
def test_the_recorded_angle_is_the_drivers(tmp_path: Path, encoder: int) -> None:
    """A wheel turned past one revolution, recorded from before its driver booted: the recorded
    MotorState angle is the live one (wrapped to [0, 360), in the units the driver read from the
    drive's 0x608F, here 1000 where the config says 4096), /joint_states the live travel (rad,
    unwrapped); the units are in the file's metadata and a decode of that file keeps them. Before:
    the config's units (4.096 times the angle) and the angle unwrapped."""
    with turned_wheel(tmp_path, encoder) as (config_path, _, capture, _, live):
        wait_for(lambda: any(m.arbitration_id in (0x281, 0x381) and m.timestamp > live.stamp
                             for m in list(capture.frames["can0"])), HANG_S, "a TPDO after the live snapshot")
    assert live.angle_deg == pytest.approx(510.0, abs=1.0)
    out = tmp_path / "wheel.mcap"
    done = decode(write_log(tmp_path / "wheel.log", capture.frames["can0"]), config_path, out)
    assert "config's units" not in done.stderr
    trimmed = without_sdo_answers(out, tmp_path / "trimmed.mcap")
    for path in (out, tmp_path / "again.mcap"):
        if path.name == "again.mcap":
            decode(trimmed, config_path, path)  # no boot in its frames: decoded by the units its metadata holds
        read = messages(path)
        motor = [m.motor for topic, m in read if topic == "/drives/wheel/status"][-1]
        joint = [m for topic, m in read if topic == "/joint_states"][-1]
        assert motor.angle == pytest.approx(live.angle_deg % 360.0, abs=0.5)
        assert (motor.stale, motor.state, motor.enabled) == (False, "OPERATION_ENABLED", True)
        assert joint.position[0] == pytest.approx(math.radians(live.angle_deg), abs=0.01)
        units = json.loads(metadata(path, "rovercan.units")["wheel"])
        assert units["objects"]["0x608F:1"] == encoder
        assert units["from"] == ("drive" if path == out else "recording")
        assert metadata(path, "rovercan.units")["drives_in_config_units"] == ""


def test_a_recording_without_the_drives_units_says_so(tmp_path: Path) -> None:
    """Frames that begin after the driver booted hold no unit object: decoded in the config's
    units, and the decode says so on stderr and in the file's metadata."""
    log = tmp_path / "late.log"
    with can.Logger(str(log)) as writer:
        for k in range(50):
            writer(can.Message(timestamp=1_800_000_000.0 + k * 0.01, arbitration_id=0x281,
                               data=(1000 * k).to_bytes(4, "little", signed=True) + bytes(4), channel="can0"))
    config_path = tmp_path / "wheel.yaml"
    config_path.write_text(GENERIC_WHEEL.replace("PORT", "29536"))
    out = tmp_path / "late.mcap"
    done = decode(log, config_path, out)
    assert "warning: wheel decoded in the config's units" in done.stderr
    assert metadata(out, "rovercan.units")["drives_in_config_units"] == "wheel"
    assert json.loads(metadata(out, "rovercan.units")["wheel"])["from"] == "config"


def test_an_incident_is_decoded_in_the_units_the_driver_read(tmp_path: Path) -> None:
    """The flight recorder's .mcap of an incident long after boot (its ring holds no unit object):
    the wheel in the units the driver read from its 0x608F, its angle the live MotorState's."""
    ring = f"recorder: {{dir: {tmp_path / 'incidents'}, seconds: 1, after_s: 0, plot: false}}\n"
    with turned_wheel(tmp_path, 1000, ring) as (_, sim, capture, driver, live):

        def ring_past_boot() -> bool:  # the ring (1 s) holds frames newer than the boot's last SDO answer
            frames = list(capture.frames["can0"])
            answered = [m.timestamp for m in frames if m.arbitration_id == 0x581]
            return bool(answered) and frames[-1].timestamp - answered[-1] > 2.0
        wait_for(ring_past_boot, HANG_S, "two seconds of frames after the boot")
        apply_action(sim, {"action": "fault", "node": 1, "code": 0x2310})
        recorder = driver.recorder
        assert recorder is not None
        wait_for(lambda: bool(recorder.written), HANG_S, "the incident written")
    mcap = recorder.written[0].with_suffix(".mcap")
    read = messages(mcap)
    # a re-boot in the ring (a starved driver's drive lost and configured again) reads the units anew
    reread = any(topic == "/can/frames" and m.id == 0x581 and int.from_bytes(bytes(m.data[1:3]), "little") == 0x608F
                 for topic, m in read)
    motor = [m.motor for topic, m in read if topic == "/drives/wheel/status"][-1]  # standing where it stopped
    assert motor.angle == pytest.approx(live.angle_deg % 360.0, abs=0.5)
    units = json.loads(metadata(mcap, "rovercan.units")["wheel"])
    assert (units["from"], units["objects"]["0x608F:1"]) == ("drive" if reread else "driver", 1000)


def test_frames_of_two_buses_come_out_in_time_order() -> None:
    """The merge alone: each bus's frames in batches after the other's, one frame of a bus a few
    ms out of its own order, a bus that falls silent (waited for no longer than the hold)."""
    from motor_driver.recording.timemerge import SLACK_S, TimeMerge

    def frame(t: float, bus: str) -> tuple[float, str, int, bool, bool, bool, int, bytes]:
        return (t, bus, 0x701, False, False, False, 1, b"\x05")

    merge = TimeMerge(hold_s=1.0, buses=["can0", "can1"])
    can0 = [frame(k * 0.01, "can0") for k in range(100)]
    can1 = [frame(k * 0.01 + 0.005, "can1") for k in range(100)]
    can1[50], can1[51] = can1[51], can1[50]  # stamped by two threads, handed over the other way round
    out = []
    for batch in range(4):
        for f in can0[batch * 25:(batch + 1) * 25] + can1[batch * 25:(batch + 1) * 25]:
            out += merge.push(f)
    assert out == sorted(out, key=lambda f: f[0]) and merge.late == 0
    silent = [frame(1.0 + k * 0.01, "can0") for k in range(200)]  # can1 says nothing more
    for f in silent:
        out += merge.push(f)
    assert out[-1][0] >= silent[-1][0] - 1.0 - SLACK_S - 0.01, "a silent bus held the other past the hold"
    out += merge.flush()
    assert len(out) == 400 and out == sorted(out, key=lambda f: f[0])

"""The kernel tier: the rover's own bus, a real kernel's SocketCAN (vcan0 here, can0 on the Orin).

Run by ``./dev kernel-test`` (part of ``./dev test``): natively where the kernel has vcan, else
inside a small VM (QEMU under software emulation, a distribution kernel with vcan, can-raw and
can-bcm, the host's root file system). Python runs about 12x slower there, so the configs use
generous periods (SYNC 50 ms, host heartbeat 100 ms, consumer times 1 s) and these tests check
behaviour, not timing. The simulator runs in a process of its own on vcan0, as `rovercan sim
--bus-interface socketcan` does for a user; so does the driver where the failure is its process's.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes

from can_config import GENERIC_EDS, load_config, load_drive_od
from can_config.errors import MotorError
from motor_driver import MotorDriver, State
from motor_driver.driver import is_kernel_bus
from virtual_can.sim import SimulatedDrive
from virtual_can.sim.runner import DriveSimulator

from .conftest import HAVE_ROS, KERNEL_BUS, KERNEL_DRIVE, REPO, SHARED_EDS, kernel_can_available, wait_for

pytestmark = [pytest.mark.kernel, pytest.mark.skipif(kernel_can_available() is not None,
                                                     reason=kernel_can_available() or "")]
CHANNEL = "vcan0"
TECHNOSOFT_EDS = SHARED_EDS / "technosoft_ipos_v1_04_via_ros2_canopen.eds"
#: Processes start slowly in the VM: python-can and canopen import in seconds there.
START_S = 60.0


def write_kernel_config(path: Path, *, nodes: tuple[int, ...] = (1,), eds: Path | None = None) -> Path:
    bus = ", ".join(f"{k}: {v}" for k, v in KERNEL_BUS.items())
    drive = ", ".join(f"{k}: {v}" for k, v in KERNEL_DRIVE.items()) + (f", eds: {eds}" if eds else "")
    drives = "".join(f"  - {{name: wheel{n}, node_id: {n}, {drive}}}\n" for n in nodes)
    path.write_text(f"buses:\n  - {{name: can0, interface: socketcan, channel: {CHANNEL}, {bus}}}\ndrives:\n{drives}")
    return path


def rovercan(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, check=False)


@contextmanager
def simulator(config: Path) -> Iterator[subprocess.Popen[str]]:
    """`rovercan sim --config CONFIG --bus-interface socketcan --bus-channel vcan0`, its own process."""
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--config", str(config), "--bus-interface",
                             "socketcan", "--bus-channel", CHANNEL], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "simulated drive" in line, (line, proc.stderr.read() if proc.poll() is not None and proc.stderr else "")
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


@dataclass
class Listener:
    """An independent raw socket on vcan0: every frame, with the kernel's receive time."""

    bus: can.BusABC = field(default_factory=lambda: can.Bus(interface="socketcan", channel=CHANNEL))
    frames: list[can.Message] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append(msg)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()

    def statuswords(self, node: int, after: float = 0.0) -> list[tuple[float, int]]:
        """(kernel time, statusword) of the event TPDO1 (0x180 + node), as the driver maps it."""
        return [(m.timestamp, int.from_bytes(m.data[:2], "little")) for m in list(self.frames)
                if m.arbitration_id == 0x180 + node and m.timestamp >= after and len(m.data) >= 2]


@pytest.fixture
def listener() -> Iterator[Listener]:
    watch = Listener()
    yield watch
    watch.close()


def test_boot_enable_move_in_each_mode_family_with_the_kernels_sync(tmp_path: Path, listener: Listener) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config), MotorDriver(load_config(config)) as driver:
        driver.start()
        handle = driver.buses["can0"]
        assert is_kernel_bus(handle.bus)
        # the SYNC is the kernel broadcast manager's, not a thread of this process
        assert type(handle.sync_task).__module__ == "can.interfaces.socketcan.socketcan", type(handle.sync_task)
        drive = driver.drive("wheel1")
        t0 = time.time()
        drive.enable()
        drive.move_to(30.0, wait=True, timeout_s=30.0)
        assert drive.snapshot().angle_deg == pytest.approx(30.0, abs=0.3)
        for _ in range(20):  # profile velocity
            drive.set_velocity(45.0)
            time.sleep(0.05)
        wait_for(lambda: drive.snapshot().velocity_deg_s > 20.0, 10.0, "turning in profile velocity")
        drive.set_velocity(0.0)
        wait_for(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, 10.0, "stopped")
        drive.set_torque(0.05)  # profile torque
        wait_for(lambda: abs(drive.snapshot().torque_nm) > 0.0, 10.0, "torque")
        drive.set_torque(0.0)
        start = drive.snapshot().angle_deg
        for i in range(1, 21):  # streamed position (CSP)
            drive.stream_position(start + i * 0.25)
            time.sleep(KERNEL_BUS["sync_period_ms"] / 1000)
        wait_for(lambda: abs(drive.snapshot().angle_deg - (start + 5.0)) < 0.5, 10.0, "the streamed target")
        assert drive.snapshot().mode == 8 and not drive.foreign_master  # its own SYNC is no other master
        elapsed = time.time() - t0
        drive.quick_stop()
    syncs = [m for m in listener.frames if m.arbitration_id == 0x080 and m.timestamp >= t0]
    assert len(syncs) >= 0.5 * elapsed / (KERNEL_BUS["sync_period_ms"] / 1000), (len(syncs), elapsed)


def test_a_second_masters_sync_is_noticed_within_a_second_and_the_drivers_own_never(tmp_path: Path) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config), MotorDriver(load_config(config)) as driver:
        driver.start()
        drive = driver.drive("wheel1")
        drive.enable()
        time.sleep(2.0)
        assert not drive.foreign_master  # two seconds of its own kernel SYNC
        with can.Bus(interface="socketcan", channel=CHANNEL) as other:  # a second driver on this host
            started = time.monotonic()
            task = other.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
                                       KERNEL_BUS["sync_period_ms"] / 1000)
            try:
                wait_for(lambda: "SYNC frames this driver did not send" in drive.foreign_master, 5.0, "noticed")
                noticed = time.monotonic() - started
            finally:
                task.stop()
        assert noticed < 1.0, noticed
        assert drive.state != State.OPERATION_ENABLED or drive.snapshot().velocity_deg_s == 0.0


@pytest.mark.parametrize("watch", ["heartbeat", "guarding"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP])
def test_a_killed_or_stopped_driver_lets_every_drive_stop_itself(tmp_path: Path, listener: Listener,
                                                                  sig: signal.Signals, watch: str) -> None:
    """Heartbeat: the generic drive's consumer (0x1016). Guarding: a drive built from the
    Technosoft iPOS EDS (0x100C/0x100D, no 0x1016), node-guarded by the driver's supervisor."""
    eds = None
    if watch == "guarding":
        if not TECHNOSOFT_EDS.is_file():
            pytest.skip(f"no {TECHNOSOFT_EDS} (../shared is not beside this clone)")
        eds = TECHNOSOFT_EDS
    config = write_kernel_config(tmp_path / "kernel.yaml", eds=eds)
    client = REPO / "tests" / "clients" / "hold_velocity.py"
    with simulator(config):
        proc = subprocess.Popen([sys.executable, str(client), str(config), "30"], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "READY":
                proc.kill()
                raise AssertionError(f"the driver process did not get ready: {proc.communicate()[1][-3000:]}")
            t_signal = time.time()
            proc.send_signal(sig)
            bound = KERNEL_DRIVE["host_timeout_ms"] / 1000 + 0.5
            deadline = time.monotonic() + bound + 5.0
            stopped_at = None
            while stopped_at is None and time.monotonic() < deadline:
                stopped_at = next((t for t, sw in listener.statuswords(1, t_signal) if sw & 0x6F != 0x27), None)
                time.sleep(0.05)
            assert stopped_at is not None, "the drive stayed enabled"
            assert stopped_at - t_signal <= bound, stopped_at - t_signal
        finally:
            if sig == signal.SIGSTOP:
                proc.send_signal(signal.SIGCONT)
            proc.kill()
            proc.communicate()


def test_can_up_creates_a_vcan_interface() -> None:
    result = rovercan("can-up", "vcan7")
    try:
        assert result.returncode == 0, result.stderr
        shown = subprocess.run(["ip", "-details", "link", "show", "vcan7"], capture_output=True, text=True, check=False)
        assert shown.returncode == 0 and "vcan" in shown.stdout and "UP" in shown.stdout, shown
        with can.Bus(interface="socketcan", channel="vcan7") as bus:  # and it carries frames
            bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
    finally:
        subprocess.run(["ip", "link", "del", "vcan7"], check=False)


def test_a_candump_of_a_session_decodes_and_replays(tmp_path: Path, listener: Listener) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    log = tmp_path / "session.log"
    with simulator(config), log.open("w") as out:
        dump = subprocess.Popen(["candump", "-L", CHANNEL], stdout=out, text=True)
        try:
            with MotorDriver(load_config(config)) as driver:
                driver.start()
                drive = driver.drive("wheel1")
                drive.enable()
                drive.move_to(10.0, wait=True, timeout_s=30.0)
            time.sleep(0.5)
        finally:
            dump.send_signal(signal.SIGINT)
            dump.wait(10)
    decoded = rovercan("decode", str(log), "--config", str(config), "--json")
    assert decoded.returncode == 0, decoded.stderr
    texts = [json.loads(line)["text"] for line in decoded.stdout.splitlines()]
    assert any("statusword" in t for t in texts) and any("SYNC" in t for t in texts), texts[:20]
    before = len(listener.frames)
    replayed = rovercan("replay", str(log), "-i", "socketcan", "-c", CHANNEL, "--fast")
    assert replayed.returncode == 0, replayed.stderr
    assert "command frames" in replayed.stderr  # NMT, RPDOs and SDO requests left out by default
    wait_for(lambda: len(listener.frames) > before + 10, 10.0, "the replayed frames on vcan0")


def ip_link(state: str) -> None:
    subprocess.run(["ip", "link", "set", CHANNEL, state], check=True)


def lost_then_configured_again(driver: MotorDriver, drive_name: str, what: str) -> None:
    """The bus counted lost and the drive refusing commands, then, once frames flow again, the
    drive configured again (booted) and not enabled: a command is refused until enable()."""
    drive = driver.drive(drive_name)
    wait_for(lambda: driver.bus_lost["can0"], 30.0, f"the bus lost after {what}")
    with pytest.raises(MotorError):
        drive.set_velocity(20.0)
    wait_for(lambda: not driver.bus_lost["can0"] and drive.booted and not drive.lost, 90.0,
             f"the drive configured again after {what}")
    assert drive.state != State.OPERATION_ENABLED
    with pytest.raises(MotorError):
        drive.set_velocity(20.0)  # not re-armed
    drive.enable()
    drive.set_velocity(20.0)  # usable again once asked


def test_the_interface_down_then_up_stops_commands_and_configures_again_unarmed(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config) as sim:
        try:
            with MotorDriver(load_config(config)) as driver:
                driver.start()
                drive = driver.drive("wheel1")
                drive.enable()
                drive.set_velocity(20.0)
                ip_link("down")
                try:
                    wait_for(lambda: driver.bus_lost["can0"], 30.0, "the bus lost")
                    time.sleep(2.0)
                finally:
                    ip_link("up")
                lost_then_configured_again(driver, "wheel1", "the interface went down and up")
                assert sim.poll() is None  # the simulator lives through it
        finally:
            subprocess.run(["ip", "link", "set", CHANNEL, "up"], check=False)
    assert "Traceback" not in caplog.text
    assert "bus can0 lost" in caplog.text


def test_error_frames_are_reported_and_a_bus_off_stops_commands(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                                 listener: Listener) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config), MotorDriver(load_config(config)) as driver, \
            can.Bus(interface="socketcan", channel=CHANNEL) as controller:  # stands in for the CAN controller
        driver.start()
        drive = driver.drive("wheel1")
        drive.enable()
        drive.set_velocity(20.0)
        controller.send(can.Message(arbitration_id=0x004, data=bytes([0, 0x20, 0, 0, 0, 0, 0, 0]),
                                    is_error_frame=True, is_extended_id=False))  # controller: error passive (tx)
        wait_for(lambda: "error passive (transmit)" in caplog.text, 20.0, "the error-passive frame reported")
        assert driver.buses["can0"].stats.error_frames == 1
        assert not driver.bus_lost["can0"]
        drive.set_velocity(20.0)  # error passive: still talking; reported, not stopped
        controller.send(can.Message(arbitration_id=0x040, data=bytes(8), is_error_frame=True, is_extended_id=False))
        lost_then_configured_again(driver, "wheel1", "a bus-off error frame")
    assert "error frame: bus-off" in caplog.text and "Traceback" not in caplog.text


@pytest.mark.skipif(not HAVE_ROS, reason="rclpy / rovercan_msgs not installed (run ./dev setup)")
def test_the_ros_drive_system_turns_and_stops_the_wheels_on_vcan0(tmp_path: Path) -> None:
    """/cmd_vel in, through the drive-system node and the driver on a socketcan config: the
    wheels turn by the kinematics and stop when /cmd_vel goes stale (rclpy graph in this process)."""
    import rclpy
    from geometry_msgs.msg import Twist

    from nodes.qos import COMMAND_QOS
    from nodes.rover_driver import DriverNode, DriveSystemNode
    from nodes.runtime import SpinThread, make_executor

    config_path = write_kernel_config(tmp_path / "kernel.yaml", nodes=(1, 2))
    # ROS entities are created with the interpreter held for seconds under the VM's emulation:
    # they are made before the driver starts, and this test's drives watch the host for 5 s
    text = config_path.read_text().replace(f"host_timeout_ms: {KERNEL_DRIVE['host_timeout_ms']}", "host_timeout_ms: 5000")
    text = text.replace(f"heartbeat_timeout_ms: {KERNEL_DRIVE['heartbeat_timeout_ms']}", "heartbeat_timeout_ms: 5000")
    config_path.write_text(text + "drive_system: {left: [wheel1], right: [wheel2], track_width_m: 0.6,"
                           " wheel_radius_m: 0.1, cmd_timeout_ms: 1000, max_accel_m_s2: 1.0, max_speed_m_s: 1.0}\n")
    config = load_config(config_path)
    assert config.drives[0].host_timeout_s == 5.0 and config.drives[0].heartbeat_timeout_s == 5.0
    os.environ.setdefault("ROS_LOG_DIR", str(tmp_path / "ros-log"))  # the VM's root file system is read-only
    with simulator(config_path), MotorDriver(config) as driver:
        context = rclpy.Context()
        rclpy.init(context=context)
        driver_node = DriverNode(driver, context=context)
        system_node = DriveSystemNode(driver, config, driver_node.refusals, context=context)
        probe = rclpy.create_node("kernel_probe", context=context)
        cmd = probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
        executor = make_executor("events", context)
        for node in (driver_node, system_node, probe):
            executor.add_node(node)
        spin = SpinThread(executor, "kernel-tier-ros")
        try:
            driver.start()
            for drive in driver:
                drive.enable()
            twist = Twist()
            twist.linear.x, twist.angular.z = 0.3, 0.5  # left (0.3 - 0.15) / 0.1 = 1.5 rad/s, right 4.5 rad/s
            t_end = time.monotonic() + 8.0
            while time.monotonic() < t_end:
                cmd.publish(twist)
                time.sleep(0.1)
            left = driver.drive("wheel1").snapshot().velocity_deg_s
            right = driver.drive("wheel2").snapshot().velocity_deg_s
            assert left > 30.0 and right > 2.0 * left, (left, right)  # turning, the right side faster
            wait_for(lambda: all(abs(d.snapshot().velocity_deg_s) < 1.0 for d in driver), 30.0,
                     "the wheels stopped after /cmd_vel went stale")
        finally:
            spin.stop(10.0)
            for node in (driver_node, system_node, probe):
                node.destroy_node()
            rclpy.shutdown(context=context)


def guarded_generic_eds(path: Path) -> Path:
    """The generic drive as a node-guarded one: 0x100C/0x100D, no heartbeat consumer (0x1016)."""
    od = canopen.import_od(str(GENERIC_EDS), 1)
    del od[0x1016]
    for index, name, data_type in ((0x100C, "Guard time", datatypes.UNSIGNED16),
                                   (0x100D, "Life time factor", datatypes.UNSIGNED8)):
        var = ODVariable(name, index)
        var.data_type, var.access_type, var.default = data_type, "rw", 0
        od.add_object(var)
    canopen.export_od(od, str(path), doc_type="eds")
    return path


@pytest.mark.parametrize("cause", ["heartbeat silent", "guard silent", "guard toggle stuck"])
def test_a_drive_that_falls_silent_while_turning_is_told_to_stop(tmp_path: Path, listener: Listener,
                                                                  cause: str) -> None:
    """The drive hears and obeys but its answers stop (a broken transmit line) or come with a
    stuck toggle: the driver declares it lost and tells it to stop (quick-stop RPDO, NMT stop,
    SDO); the simulated drive, in this process on vcan0, is read directly."""
    guarded = cause.startswith("guard")
    eds = guarded_generic_eds(tmp_path / "guarded.eds") if guarded else GENERIC_EDS
    config = write_kernel_config(tmp_path / "kernel.yaml", eds=eds)
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    with can.Bus(interface="socketcan", channel=CHANNEL) as sim_bus, DriveSimulator(sim_bus, [sim_drive]) as runner, \
            MotorDriver(load_config(config)) as driver:
        runner.start()
        driver.start()
        drive = driver.drive("wheel1")
        assert drive.guarding == guarded, drive.host_watch
        drive.enable()
        drive.set_velocity(30.0)
        wait_for(lambda: runner.call(lambda: abs(sim_drive.omega)) > 0.1, 30.0, "the shaft turning")  # type: ignore[operator]
        fault = "guard_toggle_stuck" if cause == "guard toggle stuck" else "tx_dead"
        runner.call(lambda: setattr(sim_drive.faults, fault, True))
        for _ in range(300):  # an application that keeps commanding, as a ROS node does, until refused
            try:
                drive.set_velocity(30.0)
            except MotorError:
                break
            if drive.cache.wait_until(lambda: drive.lost, 0.1):
                break
        wait_for(lambda: drive.lost, 30.0, "the drive declared lost")
        wait_for(lambda: runner.call(lambda: sim_drive.state.name != "OPERATION_ENABLED" and abs(sim_drive.omega) < 1e-3),
                 30.0, "the silent drive stopped")
    stops = [m for m in list(listener.frames) if m.arbitration_id == 0x000 and bytes(m.data) == b"\x02\x01"]
    assert stops, "no NMT stop went to the lost drive"

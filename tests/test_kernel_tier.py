"""The kernel tier: the rover's own bus, a real kernel's SocketCAN (vcan0 here, can0 on the Orin).

Run by ``./dev kernel-test`` (part of ``./dev test``): natively where the kernel has vcan, else
inside a small VM (QEMU under software emulation, a distribution kernel with vcan, can-raw and
can-bcm, the host's root file system). Python runs about 12x slower there, so the configs use
generous periods (SYNC 50 ms, host heartbeat 100 ms, consumer times 5 s: above the worst stall
measured there beside the host tier, tests/kernel_stall.py) and these tests check order and
outcome, not timing: how fast a drive stops is measured on the host tier and in benchmarks/. A
test whose drive a stall tripped anyway says so in its message (MACHINE STALL, not a product
failure). The simulator runs in a process of its own on vcan0, as `rovercan sim
--bus-interface socketcan` does for a user; so does the driver where the failure is its process's.
"""

from __future__ import annotations

import json
import math
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
import pytest

from can_config import GENERIC_EDS, load_config, load_drive_od
from can_config.errors import MotorError
from motor_driver import Drive, MotorDriver, State
from motor_driver.bus.adapters import receive_behind, watch_idle
from motor_driver.runtime.driver import is_kernel_bus
from virtual_can.sim import MotorParams, SimulatedDrive
from virtual_can.sim.runner import DriveSimulator

from .conftest import (
    HAVE_ROS,
    KERNEL_BUS,
    KERNEL_DRIVE,
    REPO,
    SHARED_EDS,
    guarded_generic_eds,
    kernel_can_available,
    kernel_controllers_available,
    publish_until,
    stop_process,
    wait_for,
)
from .kernel_stall import SEEN, Evidence, StallWatch, told_apart

pytestmark = [pytest.mark.kernel, pytest.mark.skipif(kernel_can_available() is not None,
                                                     reason=kernel_can_available() or "")]
TECHNOSOFT_EDS = SHARED_EDS / "technosoft_ipos_v1_04_via_ros2_canopen.eds"
#: Processes start slowly in the VM: python-can and canopen import in seconds there.
START_S = 60.0
#: A bound on a wait in the VM: a hang, not a timing claim (Python there is about 12x slower,
#: and a process is held a second and more at times beside the host tier).
HANG_S = 60.0
#: A frame no CANopen device of the tests sends (0x7E0: outside CiA 301's predefined set), put on
#: the bus after a session so that a reader proves it heard everything before it
MARK_ID, MARK_DATA = 0x7E0, b"MARK"
MARK_LINE = f"{MARK_ID:03X}#{MARK_DATA.hex().upper()}"


@pytest.fixture(autouse=True)
def stall_watch(request: pytest.FixtureRequest) -> Iterator[StallWatch]:
    """How long this process was held at most during the test (kept for the session's summary)."""
    watch = StallWatch()
    yield watch
    watch.close()
    SEEN.append((request.node.name, watch.worst_s))


@dataclass(frozen=True)
class Wiring:
    """Where the driver and the simulated drives are: both on one vcan interface, or the driver
    on one emulated SJA1000 controller and the drives on the other, one emulated bus between them
    (frames cross a real CAN controller driver: bitrate, echo on transmit, qlen 10)."""

    name: str
    driver: str  # the driver's interface (the config's channel)
    drives: str  # the simulated drives' interface

    def __str__(self) -> str:
        return self.name


VCAN = Wiring("vcan0", "vcan0", "vcan0")
SJA1000 = Wiring("sja1000", "can0", "can1")
NEEDS_CONTROLLERS = pytest.mark.skipif(kernel_controllers_available() is not None,
                                       reason=kernel_controllers_available() or "")
#: A test marked so runs on vcan0 and on the SJA1000 pair (where the VM has it).
BOTH_WIRINGS = pytest.mark.parametrize("wiring", [VCAN, pytest.param(SJA1000, marks=NEEDS_CONTROLLERS)], ids=str)


@pytest.fixture
def wiring() -> Wiring:
    """A test not parametrized by BOTH_WIRINGS: vcan0."""
    return VCAN


def bring_up(wiring: Wiring) -> None:
    """The SJA1000 pair at 1 Mbit/s with restart-ms 100, as `rovercan can-up` sets a controller
    (left as it is when it already is: a controller's bitrate cannot change while it is up)."""
    if wiring is VCAN:
        return
    from motor_driver.bus.link import read_kernel_health

    for name in (wiring.driver, wiring.drives):
        health = read_kernel_health(name)
        if health.link_up and health.bitrate == 1_000_000:
            continue
        subprocess.run(["ip", "link", "set", name, "down"], check=True)
        subprocess.run(["ip", "link", "set", name, "type", "can", "bitrate", "1000000", "restart-ms", "100"], check=True)
        subprocess.run(["ip", "link", "set", name, "up"], check=True)


def write_kernel_config(path: Path, *, nodes: tuple[int, ...] = (1,), eds: Path | None = None,
                        wiring: Wiring = VCAN) -> Path:
    bring_up(wiring)
    bus = ", ".join(f"{k}: {v}" for k, v in KERNEL_BUS.items())
    drive = ", ".join(f"{k}: {v}" for k, v in KERNEL_DRIVE.items()) + (f", eds: {eds}" if eds else "")
    drives = "".join(f"  - {{name: wheel{n}, node_id: {n}, {drive}}}\n" for n in nodes)
    path.write_text(f"buses:\n  - {{name: can0, interface: socketcan, channel: {wiring.driver}, {bus}}}\n"
                    f"drives:\n{drives}")
    return path


def rovercan(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, check=False)


@contextmanager
def simulator(config: Path, wiring: Wiring = VCAN) -> Iterator[DriveSimulator]:
    """The config's drives simulated in this process on the wiring's drive side, the way
    `rovercan sim --bus-interface socketcan` runs them (one DriveSimulator on a python-can
    SocketCAN bus); a process start costs 5-15 s in the VM, so only the tests of the user's
    command (and of a driver sharing no interpreter with them) use :func:`sim_process`."""
    loaded = load_config(config)
    drives = [SimulatedDrive(d.node_id, load_drive_od(d.eds, d.node_id), MotorParams.from_model(d.sim, d.counts_per_rev),
                             name=d.name) for d in loaded.drives]
    # ordinary scheduling, as the driver beside it in this process has (DriveSimulator's realtime)
    with can.Bus(interface="socketcan", channel=wiring.drives) as bus, \
            DriveSimulator(bus, drives, realtime=False) as runner:
        runner.start()
        yield runner


@contextmanager
def sim_process(config: Path, wiring: Wiring = VCAN) -> Iterator[subprocess.Popen[str]]:
    """`rovercan sim --config CONFIG --bus-interface socketcan --bus-channel IF`, its own process,
    on the wiring's drive side."""
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--config", str(config), "--bus-interface",
                             "socketcan", "--bus-channel", wiring.drives], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "simulated drive" in line, (line, proc.stderr.read() if proc.poll() is not None and proc.stderr else "")
        yield proc
    finally:
        stop_process(proc)


@dataclass
class Listener:
    """An independent raw socket on the driver's interface: every frame (the drives' from the
    wire, the driver's by the kernel's echo), with the kernel's receive time."""

    channel: str = VCAN.driver
    bus: can.BusABC = field(init=False)
    frames: list[can.Message] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)
    #: the wall-clock time (the kernel stamps' clock) a read began that found nothing queued: every
    #: frame the kernel received before it had been read (None until one has)
    heard_until: float | None = None

    def __post_init__(self) -> None:
        self.bus = can.Bus(interface="socketcan", channel=self.channel)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            began = time.time()
            try:
                msg = self.bus.recv(0.0)
                if msg is None:  # nothing queued: all the kernel received before `began` was read
                    self.heard_until = began
                    msg = self.bus.recv(0.05)
            except can.CanOperationError:  # the interface went down (ENETDOWN, once): it listens on when it is up
                self.stop.wait(0.05)
                continue
            if msg is not None:
                self.frames.append(msg)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()

    def evidence(self, watch: StallWatch, node: int = 1) -> Evidence:
        """What this bus shows of a stall, against the kernel configs' consumer times."""
        return Evidence(lambda: list(self.frames), node, KERNEL_DRIVE["host_timeout_ms"] / 1000,
                        KERNEL_DRIVE["heartbeat_timeout_ms"] / 1000, watch, lambda: self.heard_until)

    def statuswords(self, node: int, after: float = 0.0) -> list[tuple[float, int]]:
        """(kernel time, statusword) of the event TPDO1 (0x180 + node), as the driver maps it."""
        return [(m.timestamp, int.from_bytes(m.data[:2], "little")) for m in list(self.frames)
                if m.arbitration_id == 0x180 + node and m.timestamp >= after and len(m.data) >= 2]


@pytest.fixture
def listener(wiring: Wiring) -> Iterator[Listener]:
    bring_up(wiring)
    watch = Listener(wiring.driver)
    yield watch
    watch.close()


@BOTH_WIRINGS
def test_boot_enable_move_in_each_mode_family_with_the_kernels_sync(tmp_path: Path, listener: Listener,
                                                                    wiring: Wiring, stall_watch: StallWatch) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml", wiring=wiring)
    with sim_process(config, wiring), MotorDriver(load_config(config)) as driver, \
            told_apart(listener.evidence(stall_watch)):
        driver.start()
        handle = driver.buses["can0"]
        assert is_kernel_bus(handle.bus)
        # the SYNC is the kernel broadcast manager's, not a thread of this process
        assert type(handle.sync_task).__module__ == "can.interfaces.socketcan.socketcan", type(handle.sync_task)
        drive = driver.drive("wheel1")
        t0 = time.time()
        drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
        drive.move_to(30.0, wait=True, timeout_s=HANG_S)
        assert drive.snapshot().angle_deg == pytest.approx(30.0, abs=0.3)
        for _ in range(20):  # profile velocity
            drive.set_velocity(45.0)
            time.sleep(0.05)
        wait_for(lambda: drive.snapshot().velocity_deg_s > 20.0, HANG_S, "turning in profile velocity")
        drive.set_velocity(0.0)
        wait_for(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, HANG_S, "stopped")
        drive.set_torque(0.05)  # profile torque
        wait_for(lambda: abs(drive.snapshot().torque_nm) > 0.0, HANG_S, "torque")
        drive.set_torque(0.0)
        # the shaft coasts on after the torque (a full turn and more while a slow VM waited for
        # the torque): a stream starts from where it has come to rest, as a user's would
        wait_for(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, HANG_S, "the shaft at rest after the torque")
        # a continuous joint takes its targets within a turn and goes the short way: the same place
        start = math.remainder(drive.snapshot().angle_deg, 360.0)
        t_stream = time.time()
        for i in range(1, 21):  # streamed position (CSP)
            drive.stream_position(start + i * 0.25)
            time.sleep(KERNEL_BUS["sync_period_ms"] / 1000)
        t1 = time.time()
        wait_for(lambda: abs(math.remainder(drive.snapshot().angle_deg - (start + 5.0), 360.0)) < 0.5, HANG_S,
                 "the streamed target")
        assert drive.snapshot().mode == 8 and not drive.watch.foreign_master  # its own SYNC is no other master
        drive.quick_stop(HANG_S)
    # the kernel's SYNC went on through the steps: while the drive was enabled before the stream,
    # and during the stream (a second of set-points, one per SYNC period)
    syncs = [m.timestamp for m in listener.frames if m.arbitration_id == 0x080]
    enabled = next(t for t, sw in listener.statuswords(1, t0) if sw & 0x6F == 0x27)
    assert any(enabled < t < t_stream for t in syncs), "no SYNC between the enable and the stream"
    assert any(t_stream < t < t1 for t in syncs), "no SYNC during the stream"


@BOTH_WIRINGS
def test_rovercan_move_turns_the_drive_and_reads_the_angle_back(tmp_path: Path, listener: Listener,
                                                               wiring: Wiring) -> None:
    """The bench command a user runs first on a new bus: `rovercan move` by the config's drive name
    (its units, its bus); the drive's own TPDOs on the driver's interface show it enabled, then
    disabled again when the command is done."""
    config = write_kernel_config(tmp_path / "kernel.yaml", wiring=wiring)
    with simulator(config, wiring):
        # --wait: a bound for a hang (the VM is software-emulated); the outcome is the verdict
        moved = rovercan("move", "wheel1", "30", "--config", str(config), "--json", "--wait", "120", timeout=300)
    assert moved.returncode == 0, moved.stderr[-3000:]
    assert json.loads(moved.stdout)["angle_deg"] == pytest.approx(30.0, abs=0.5), moved.stdout
    words = [sw for _, sw in listener.statuswords(1)]
    enabled = [i for i, sw in enumerate(words) if sw & 0x6F == 0x27]
    assert enabled, "the drive never reported Operation Enabled"
    assert any(sw & 0x6F != 0x27 for sw in words[enabled[-1] + 1:]), "the drive was left enabled"


def test_a_second_masters_sync_is_noticed_and_the_drivers_own_never(tmp_path: Path, listener: Listener,
                                                                    stall_watch: StallWatch) -> None:
    """Order and outcome on the kernel's loopback: 40 SYNCs of its own (the broadcast manager's)
    leave the driver calm; a second driver's SYNC on this host is noticed. How soon (within the
    rate window, under a second) is checked frame by frame in tests/test_kernel_sync.py."""
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config), MotorDriver(load_config(config)) as driver:
        driver.start()
        drive = driver.drive("wheel1")
        enable_for_setup(drive, listener.evidence(stall_watch))
        enabled = time.time()
        wait_for(lambda: sum(m.arbitration_id == 0x080 and m.timestamp > enabled for m in list(listener.frames)) >= 40,
                 HANG_S, "40 SYNCs of the driver's own")
        assert not drive.watch.foreign_master  # its own kernel SYNC is no other master
        with can.Bus(interface="socketcan", channel=VCAN.driver) as other:  # a second driver on this host
            task = other.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
                                       KERNEL_BUS["sync_period_ms"] / 1000)
            try:
                wait_for(lambda: "SYNC frames this driver did not send" in drive.watch.foreign_master, HANG_S, "noticed")
            finally:
                task.stop()
        assert drive.cache.state != State.OPERATION_ENABLED or drive.snapshot().velocity_deg_s == 0.0


@pytest.mark.parametrize(("wiring", "sig", "watch"), [
    *((VCAN, sig, watch) for sig in (signal.SIGKILL, signal.SIGSTOP) for watch in ("heartbeat", "guarding")),
    pytest.param(SJA1000, signal.SIGKILL, "heartbeat", marks=NEEDS_CONTROLLERS)],
    ids=lambda v: v.name if isinstance(v, signal.Signals) else str(v))
def test_a_killed_or_stopped_driver_lets_every_drive_stop_itself(tmp_path: Path, listener: Listener, wiring: Wiring,
                                                                  sig: signal.Signals, watch: str,
                                                                  stall_watch: StallWatch) -> None:
    """Heartbeat: the generic drive's consumer (0x1016). Guarding: a drive built from the
    Technosoft iPOS EDS (0x100C/0x100D, no 0x1016), node-guarded by the driver's supervisor.
    On the SJA1000 pair: the driver's process on can0 killed, the drive on can1. Order and
    outcome: enabled until the signal, then stopped by itself saying why (EMCY 0x8130); how soon
    after its consumer time is measured on the host tier (tests/test_host_loss.py), not here."""
    eds = None
    if watch == "guarding":
        if not TECHNOSOFT_EDS.is_file():
            pytest.skip(f"no {TECHNOSOFT_EDS} (../shared is not beside this clone)")
        eds = TECHNOSOFT_EDS
    config = write_kernel_config(tmp_path / "kernel.yaml", eds=eds, wiring=wiring)
    client = REPO / "tests" / "clients" / "hold_velocity.py"
    with simulator(config, wiring):
        proc = subprocess.Popen([sys.executable, str(client), str(config), "30"], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "READY":
                proc.kill()
                raise AssertionError(f"the driver process did not get ready: {proc.communicate()[1][-3000:]}")
            # the client is ready once its driver saw Operation Enabled; the drive's next TPDO says it
            # on the wire too (a SYNC later; in the emulated VM that can come after READY)
            wait_for(lambda: any(sw & 0x6F == 0x27 for _, sw in listener.statuswords(1)), HANG_S,
                     "the drive's statusword Operation Enabled on the wire")
            t_signal = time.time()
            with told_apart(listener.evidence(stall_watch)):  # a stall before the signal: said as one
                words = [sw for t, sw in listener.statuswords(1) if t < t_signal]
                assert words and words[-1] & 0x6F == 0x27, "the drive had stopped before its driver was signalled"
            proc.send_signal(sig)

            def stopped() -> float | None:
                return next((t for t, sw in listener.statuswords(1, t_signal) if sw & 0x6F != 0x27), None)

            wait_for(lambda: stopped() is not None, KERNEL_DRIVE["host_timeout_ms"] / 1000 + HANG_S,
                     f"the drive stopping itself after its driver's {sig.name}")
            emcy = [m for m in list(listener.frames) if m.arbitration_id == 0x081 and m.timestamp >= t_signal]
            assert any(bytes(m.data[:2]) == b"\x30\x81" for m in emcy), f"no EMCY 0x8130 (host lost) after it: {emcy}"
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
        dump = subprocess.Popen(["candump", "-L", VCAN.driver], stdout=out, text=True)
        try:
            with MotorDriver(load_config(config)) as driver:
                driver.start()
                drive = driver.drive("wheel1")
                drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
                drive.move_to(10.0, wait=True, timeout_s=30.0)
            # a marker after the session: candump writes and flushes each frame as it reads it, so
            # once the marker's line is in the log every frame of the session before it is too
            with can.Bus(interface="socketcan", channel=VCAN.driver) as bus:
                bus.send(can.Message(arbitration_id=MARK_ID, data=MARK_DATA, is_extended_id=False))
            wait_for(lambda: MARK_LINE in log.read_text(), HANG_S, "candump's line of the marker frame")
        finally:
            dump.send_signal(signal.SIGINT)
            dump.wait(10)
    decoded = rovercan("decode", str(log), "--config", str(config), "--json")
    assert decoded.returncode == 0, decoded.stderr
    texts = [json.loads(line)["text"] for line in decoded.stdout.splitlines()]
    assert any("statusword" in t for t in texts) and any("SYNC" in t for t in texts), texts[:20]
    before = len(listener.frames)
    replayed = rovercan("replay", str(log), "-i", "socketcan", "-c", VCAN.driver, "--fast")
    assert replayed.returncode == 0, replayed.stderr
    assert "command frames" in replayed.stderr  # NMT, RPDOs and SDO requests left out by default
    wait_for(lambda: len(listener.frames) > before + 10, HANG_S, "the replayed frames on vcan0")


def ip_link(state: str, interface: str = VCAN.driver) -> None:
    subprocess.run(["ip", "link", "set", interface, state], check=True)


def enable_for_setup(drive: Drive, evidence: Evidence, tries: int = 3) -> None:
    """An enable that only sets a test up (its subject comes after): one a machine stall
    interrupted, as the bus itself shows (:meth:`Evidence.verdict`: a heartbeat silent on the
    wire for longer than its consumer time, or this process held longer), is waited out (the
    drive configured again) and asked again; any other refusal, or a stall every time, fails the
    test with the verdict. Measured: the emulated SJA1000 pair carried neither side's heartbeats
    for 5 s beside two busy loops per core, and the setup's enable was refused "the drive was lost"."""
    for attempt in range(1, tries + 1):
        try:
            drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
            return
        except MotorError as err:
            verdict = evidence.verdict()
            if not verdict.startswith("MACHINE STALL") or attempt == tries:
                raise AssertionError(f"the setup's enable, try {attempt} of {tries}: {verdict}\n"
                                     f"{type(err).__name__}: {err}") from err
            print(f"the setup's enable, try {attempt}: {verdict}; {err}; asked again", file=sys.stderr)
            wait_for(lambda: drive.cache.booted and not drive.cache.lost, 2 * HANG_S,
                     "the drive configured again after a machine stall")
            if drive.cache.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                drive.recover(HANG_S)  # the drive stopped itself, hearing no host: its fault acknowledged


def lost_then_configured_again(driver: MotorDriver, drive_name: str, what: str) -> None:
    """The bus counted lost and the drive refusing commands, then, once frames flow again, the
    drive configured again (booted) and not enabled: a command is refused until enable()."""
    drive = driver.drive(drive_name)
    wait_for(lambda: driver.bus_lost["can0"], 30.0, f"the bus lost after {what}")
    with pytest.raises(MotorError):
        drive.set_velocity(20.0)
    wait_for(lambda: not driver.bus_lost["can0"] and drive.cache.booted and not drive.cache.lost, 90.0,
             f"the drive configured again after {what}")
    assert drive.cache.state != State.OPERATION_ENABLED
    with pytest.raises(MotorError):
        drive.set_velocity(20.0)  # not re-armed
    drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
    drive.set_velocity(20.0)  # usable again once asked


def test_the_interface_down_then_up_stops_commands_and_configures_again_unarmed(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with sim_process(config) as sim:
        try:
            with MotorDriver(load_config(config)) as driver:
                driver.start()
                drive = driver.drive("wheel1")
                drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
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
            subprocess.run(["ip", "link", "set", VCAN.driver, "up"], check=False)
    assert "Traceback" not in caplog.text
    assert "bus can0 lost" in caplog.text


class Output:
    """A process's stdout and stderr, line by line, gathered by a thread (waited on by condition)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        self.lines: list[str] = []
        self._stream = proc.stdout
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self._stream:
            self.lines.append(line.rstrip("\n"))

    def has(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def text(self) -> str:
        return "\n".join(self.lines[-60:])


@BOTH_WIRINGS
def test_the_drivers_link_down_for_2_s_under_an_application_that_keeps_commanding(
        tmp_path: Path, listener: Listener, wiring: Wiring) -> None:
    """An application (its own process, the API) keeps commanding a velocity; the driver's
    interface goes down for 2 s, and longer until the drive, hearing no host, has stopped itself
    (its consumer time is above the VM's stalls), and comes back (on the SJA1000 pair: can0, the
    drive on can1). The driver says the link went down, lives, configures
    the drive again when the link is back and leaves it stopped while the application goes on
    commanding (each command refused)."""
    config = write_kernel_config(tmp_path / "kernel.yaml", wiring=wiring)
    client = REPO / "tests" / "clients" / "hold_velocity.py"
    with simulator(config, wiring) as runner:
        proc = subprocess.Popen([sys.executable, str(client), str(config), "30", "--keep-commanding"], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        out = Output(proc)
        try:
            wait_for(lambda: out.has("READY") or proc.poll() is not None, 2 * START_S, "the drive turning", out.text)
            assert out.has("READY"), out.text()
            ip_link("down", wiring.driver)
            try:
                wait_for(lambda: out.has("link down"), 60.0, "the driver saying the link went down", out.text)
                down_until = time.monotonic() + 2.0  # the scenario: the link stays down for 2 s at least

                def stopped_itself() -> bool:
                    assert proc.poll() is None, out.text()  # and the application lives through it
                    state = runner.call(lambda: runner.drive(1).state.name, HANG_S)
                    return time.monotonic() >= down_until and state != "OPERATION_ENABLED"

                wait_for(stopped_itself, KERNEL_DRIVE["host_timeout_ms"] / 1000 + HANG_S,
                         "the drive stopping itself, hearing no host", out.text)
            finally:
                ip_link("up", wiring.driver)
            wait_for(lambda: out.has("re-established") or proc.poll() is not None, 120.0, "the bus back", out.text)
            assert out.has("re-established"), out.text()
            back = time.time()
            wait_for(lambda: sum(m.arbitration_id == 0x281 and m.timestamp > back for m in list(listener.frames)) >= 20,
                     60.0, "20 SYNC TPDOs of the drive after the bus came back")
            assert proc.poll() is None, out.text()  # the application and its driver live
        finally:
            proc.kill()
            proc.wait()
    assert [sw for _, sw in listener.statuswords(1, back) if sw & 0x6F == 0x27] == [], "enabled again"
    speeds = [int.from_bytes(m.data[4:8], "little", signed=True) for m in list(listener.frames)
              if m.arbitration_id == 0x281 and m.timestamp > back and len(m.data) >= 8]
    assert speeds and all(abs(v) < 5 for v in speeds[-10:]), speeds[-10:]  # counts/s: standing still
    assert out.has("REFUSED") and "Traceback" not in out.text(), out.text()


@pytest.mark.parametrize("wiring", [pytest.param(SJA1000, marks=NEEDS_CONTROLLERS)], ids=str)
def test_a_full_transmit_queue_is_counted_and_said_never_a_crash(
        tmp_path: Path, wiring: Wiring, caplog: pytest.LogCaptureFixture, listener: Listener,
        stall_watch: StallWatch) -> None:
    """The controller's transmit queue full (ENOBUFS): a token-bucket qdisc at 1 kbit/s on can0
    holds two frames, so the kernel refuses the driver's sends. Each refusal is counted (and
    retried for a moment), the driver says so and stays up; a queue that stays full for host
    heartbeats in a row loses the bus (nothing it sends gets out); once the queue drains, the
    drive is configured again and not enabled."""
    config = write_kernel_config(tmp_path / "kernel.yaml", wiring=wiring)
    with simulator(config, wiring), MotorDriver(load_config(config)) as driver:
        driver.start()
        drive = driver.drive("wheel1")
        enable_for_setup(drive, listener.evidence(stall_watch))
        network = driver.buses["can0"].network
        subprocess.run(["tc", "qdisc", "add", "dev", wiring.driver, "root", "tbf", "rate", "1kbit", "burst", "32",
                        "limit", "32"], check=True)
        try:
            for _ in range(600):  # an application commanding until the driver refuses
                try:
                    drive.set_velocity(10.0)
                except MotorError:
                    break
                if drive.cache.wait_until(lambda: network.tx_queue_full > 0 and driver.bus_lost["can0"], 0.05):
                    break
            wait_for(lambda: network.tx_queue_full > 0, 30.0, "a send refused for a full queue")
            wait_for(lambda: "transmit queue full (ENOBUFS)" in caplog.text, 30.0, "the full queue said")
            # a refused command can end the loop first: the queue stays full until the bus is lost
            wait_for(lambda: driver.bus_lost["can0"], 60.0, "the bus lost (nothing the driver sends gets out)")
        finally:
            subprocess.run(["tc", "qdisc", "del", "dev", wiring.driver, "root"], check=True)
        wait_for(lambda: not driver.bus_lost["can0"] and drive.cache.booted and not drive.cache.lost, 120.0, "the bus usable again")
        assert drive.cache.state != State.OPERATION_ENABLED
    assert "Traceback" not in caplog.text

def test_a_kernel_sockets_reader_is_behind_until_it_waits_with_nothing_unread() -> None:
    """The evidence an SDO waiter past its deadline reads on the kernel's path (a CAN raw socket
    read by python-can, watched as the driver's receive thread watches it;
    motor_driver.bus.adapters.receive_behind). A reader in its marked wait with nothing unread is
    not behind. One that took a frame from the socket and has not handed it on is (held here right
    after python-can's read, as a thread waiting for the interpreter after its recvmsg is). A frame
    unread in the socket while the thread waits is too."""
    from motor_driver.bus import adapters

    raw = can.Bus(interface="socketcan", channel=VCAN.driver)
    took, release = threading.Event(), threading.Event()
    own = raw._recv_internal

    def held_after_its_read(timeout: float | None) -> tuple[can.Message | None, bool]:
        got: tuple[can.Message | None, bool] = own(timeout)
        if got[0] is not None and got[0].arbitration_id == MARK_ID + 1:
            took.set()
            release.wait(HANG_S)
        return got

    raw._recv_internal = held_after_its_read  # type: ignore[method-assign]
    bus = watch_idle(raw, lambda began: None)
    writer = can.Bus(interface="socketcan", channel=VCAN.driver)
    got: list[can.Message | None] = []

    def read(n: int) -> None:
        got.extend(bus.recv(HANG_S) for _ in range(n))

    try:
        assert receive_behind(bus) is True  # nobody reads it yet (and its waits are marked from now on)
        reader = threading.Thread(target=read, args=(2,), daemon=True)
        reader.start()
        wait_for(lambda: receive_behind(bus) is False, HANG_S, "the reader in its wait, nothing unread")
        writer.send(can.Message(arbitration_id=MARK_ID, data=MARK_DATA, is_extended_id=False))
        wait_for(lambda: len(got) == 1, HANG_S, "the first frame handed on")
        writer.send(can.Message(arbitration_id=MARK_ID + 1, data=MARK_DATA, is_extended_id=False))
        wait_for(took.is_set, HANG_S, "the second frame taken from the socket, not yet handed on")
        assert receive_behind(bus) is True  # the frame is in the thread's hands: behind
        release.set()
        reader.join(HANG_S)
        assert [m.arbitration_id for m in got if m is not None] == [MARK_ID, MARK_ID + 1]
        getattr(bus, adapters._RECEIVE_STATE).waiting = True  # as in its wait: only the socket tells
        writer.send(can.Message(arbitration_id=MARK_ID, data=MARK_DATA, is_extended_id=False))
        wait_for(lambda: receive_behind(bus) is True, HANG_S, "a frame unread in the socket")
    finally:
        release.set()
        writer.shutdown()
        bus.shutdown()


def test_error_frames_are_reported_and_a_bus_off_stops_commands(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                                 listener: Listener, stall_watch: StallWatch) -> None:
    config = write_kernel_config(tmp_path / "kernel.yaml")
    with simulator(config), MotorDriver(load_config(config)) as driver, \
            can.Bus(interface="socketcan", channel=VCAN.driver) as controller:  # stands in for the CAN controller
        driver.start()
        drive = driver.drive("wheel1")
        enable_for_setup(drive, listener.evidence(stall_watch))
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


@BOTH_WIRINGS
@pytest.mark.skipif(not HAVE_ROS, reason="rclpy / rovercan_msgs not installed (run ./dev setup)")
def test_the_ros_drive_system_turns_and_stops_the_wheels(tmp_path: Path, wiring: Wiring) -> None:
    """/cmd_vel in, through the drive-system node and the driver on a socketcan config: the
    wheels turn by the kinematics and stop when /cmd_vel goes stale (rclpy graph in this process)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist

    from nodes.joints.driver_node import DriverNode
    from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS
    from nodes.process.spinning import SpinThread, make_executor
    from nodes.rover.drive_system import DriveSystemNode

    config_path = write_kernel_config(tmp_path / "kernel.yaml", nodes=(1, 2), wiring=wiring)
    # ROS entities are created with the interpreter held for seconds under the VM's emulation:
    # they are made before the driver starts, and the drives watch the host for 5 s (KERNEL_DRIVE);
    # /cmd_vel goes stale after 3 s, above the VM's stalls, not the shipped 0.5 s
    config_path.write_text(config_path.read_text() + "drive_system: {left: [wheel1], right: [wheel2], track_width_m: 0.6,"
                           " wheel_radius_m: 0.1, cmd_timeout_ms: 3000, max_accel_m_s2: 1.0, max_speed_m_s: 1.0}\n")
    config = load_config(config_path)
    assert config.drives[0].host_timeout_s == 5.0 and config.drives[0].heartbeat_timeout_s == 5.0
    os.environ.setdefault("ROS_LOG_DIR", str(tmp_path / "ros-log"))  # the VM's root file system is read-only
    with sim_process(config_path, wiring), MotorDriver(config) as driver:
        context = rclpy.Context()
        rclpy.init(context=context)
        driver_node = DriverNode(driver, context=context)
        system_node = DriveSystemNode(driver, config, driver_node.refusals, driver_node.handoff, context=context)
        assert system_node.tick_with(driver_node)  # as rover_driver runs it
        probe = rclpy.create_node("kernel_probe", context=context)
        cmd = probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
        bus_status: list[dict[str, str]] = []  # the bus's status on /diagnostics, as key -> value
        probe.create_subscription(DiagnosticArray, "/diagnostics", lambda array: bus_status.extend(
            {kv.key: kv.value for kv in st.values} | {"message": st.message} for st in array.status
            if st.name == "rovercan: bus can0"), DIAGNOSTICS_QOS)
        executor = make_executor("events", context)
        for node in (driver_node, system_node, probe):
            executor.add_node(node)
        spin = SpinThread(executor, "kernel-tier-ros")
        try:
            driver.start()
            for drive in driver:
                drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
            twist = Twist()
            twist.linear.x, twist.angular.z = 0.3, 0.5  # left (0.3 - 0.15) / 0.1 = 1.5 rad/s, right 4.5 rad/s

            def turning() -> bool:  # the right side faster
                left = driver.drive("wheel1").snapshot().velocity_deg_s
                right = driver.drive("wheel2").snapshot().velocity_deg_s
                return left > 30.0 and right > 2.0 * left

            publish_until(lambda: cmd.publish(twist), turning, HANG_S, "the wheels turning the rover left",
                          period_s=0.1)
            wait_for(lambda: all(abs(d.snapshot().velocity_deg_s) < 1.0 for d in driver), 30.0,
                     "the wheels stopped after /cmd_vel went stale")
            wait_for(lambda: bool(bus_status), 30.0, "the bus's status on /diagnostics")
            status = bus_status[-1]  # one status per bus, with what the kernel says of it
            if wiring is SJA1000:
                assert (status["can_state"], status["bitrate"], status["link"]) == ("ERROR-ACTIVE", "1000000", "up")
                assert status["tx_errors"] == status["rx_errors"] == "0" and status["restart_ms"] == "100", status
            else:
                assert status["can_state"] == "none (no controller)" and status["link"] == "up", status
            assert int(status["frames_received"]) > 0 and status["tx_not_sent"] == "0", status
        finally:
            spin.stop(10.0)
            for node in (driver_node, system_node, probe):
                node.destroy_node()
            rclpy.shutdown(context=context)


@pytest.mark.parametrize(("wiring", "cause"), [
    *((VCAN, cause) for cause in ("heartbeat silent", "guard silent", "guard toggle stuck")),
    pytest.param(SJA1000, "heartbeat silent", marks=NEEDS_CONTROLLERS)], ids=str)
def test_a_drive_that_falls_silent_while_turning_is_told_to_stop(tmp_path: Path, listener: Listener, wiring: Wiring,
                                                                  cause: str) -> None:
    """The drive hears and obeys but its answers stop (a broken transmit line) or come with a
    stuck toggle: the driver declares it lost and tells it to stop (quick-stop RPDO, NMT stop,
    SDO); the simulated drive, in this process on vcan0, is read directly."""
    guarded = cause.startswith("guard")
    eds = guarded_generic_eds(tmp_path / "guarded.eds") if guarded else GENERIC_EDS
    config = write_kernel_config(tmp_path / "kernel.yaml", eds=eds, wiring=wiring)
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    with can.Bus(interface="socketcan", channel=wiring.drives) as sim_bus, DriveSimulator(sim_bus, [sim_drive], realtime=False) as runner, \
            MotorDriver(load_config(config)) as driver:
        runner.start()
        driver.start()
        drive = driver.drive("wheel1")
        assert drive.cache.guarding == guarded, drive.watch.host_watch
        drive.enable(HANG_S)  # per transition: the VM's emulation starves at times
        drive.set_velocity(30.0)
        wait_for(lambda: runner.call(lambda: abs(sim_drive.omega), HANG_S) > 0.1, HANG_S, "the shaft turning")  # type: ignore[operator]
        fault = "guard_toggle_stuck" if cause == "guard toggle stuck" else "tx_dead"
        runner.call(lambda: setattr(sim_drive.faults, fault, True), HANG_S)
        for _ in range(300):  # an application that keeps commanding, as a ROS node does, until refused
            try:
                drive.set_velocity(30.0)
            except MotorError:
                break
            if drive.cache.wait_until(lambda: drive.cache.lost, 0.1):
                break
        wait_for(lambda: drive.cache.lost, 30.0, "the drive declared lost")
        wait_for(lambda: runner.call(lambda: sim_drive.state.name != "OPERATION_ENABLED" and abs(sim_drive.omega) < 1e-3,
                                     HANG_S), HANG_S, "the silent drive stopped")
    stops = [m for m in list(listener.frames) if m.arbitration_id == 0x000 and bytes(m.data) == b"\x02\x01"]
    assert stops, "no NMT stop went to the lost drive"

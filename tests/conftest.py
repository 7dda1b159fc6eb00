"""Shared fixtures: a simulator served over the real socketcand protocol, and a driver on it."""

from __future__ import annotations

import itertools
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes
from hypothesis import HealthCheck, settings

from can_config import GENERIC_EDS, RoverConfig, load_config, parse_config, with_bus_overrides
from motor_driver import MotorDriver
from motor_driver.drive import Drive
from motor_driver.process import heap
from rovercan.launch import LOCAL_DISCOVERY
from virtual_can import BusEngine, SimService, SocketcandServer, VirtualBus
from virtual_can.server import RAWMODE_HOLD_S

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
SHARED_EDS = SHARED / "eds"
SHARED_TRAFFIC = SHARED / "traffic"

# Hypothesis's own clock off for every property test: its 200 ms deadline per example and its
# too-slow health check are wall-clock verdicts, and a crowded runner fails them at random
settings.register_profile("rovercan", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("rovercan")

def _have_ros() -> bool:
    """rclpy and the interface package import here (a venv without the ROS wheels: no)."""
    try:
        import rclpy  # noqa: F401
        import rovercan_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


HAVE_ROS = _have_ros()
requires_ros = pytest.mark.skipif(not HAVE_ROS, reason="rclpy / rovercan_msgs not installed (run ./dev setup)")
requires_shared = pytest.mark.skipif(not SHARED_EDS.is_dir(),
                                     reason="../shared/eds is absent (only the team's checkout has it)")

logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
# the flight recorder of every driver the suite starts (subprocesses inherit it) writes its
# incidents here, not into the user's ~/.local/state
os.environ.setdefault("ROVERCAN_INCIDENT_DIR", tempfile.mkdtemp(prefix="rovercan-test-incidents-"))
# DDS discovery on loopback only, for every graph the suite starts (subprocesses inherit it):
# by default Fast DDS multicasts on every interface, and the tests' traffic stays on this machine
os.environ.setdefault(*LOCAL_DISCOVERY)
# pytest-xdist runs modules side by side (./dev test): each worker's ROS graphs in a DDS domain
# of their own, or one worker's /cmd_vel would reach another's driver; and each run's workers in
# domains of their own too (10-99, by the run's id), or a second run on this machine (another
# clone's CI, a developer's tests) reaches them: one's /arm aborted the other's trajectory goal
if (_worker := os.environ.get("PYTEST_XDIST_WORKER", "")).startswith("gw"):
    _workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "2")))
    _run = zlib.crc32(os.environ.get("PYTEST_XDIST_TESTRUNUID", "").encode()) % max(1, 90 // _workers)
    os.environ["ROS_DOMAIN_ID"] = str(10 + _run * _workers + int(_worker[2:]) % _workers)
# load_config() reads $ROVERCAN_CONFIG when set: the suite's calls mean the embedded default
os.environ.pop("ROVERCAN_CONFIG", None)


#: The drives' host-watch consumer time in rigs built by make_config: the driver (ordinary threads)
#: and the test share one interpreter on two cores with the simulator, which runs real-time and
#: judges the host's heartbeats on the bus's time line, so the host is as late as its starved
#: process really sent them: 100-150 ms with one core busy, 330 ms and more at a load of 11 on two
#: cores (a drive that stopped itself then failed a test). The ROS graphs' rigs use 2 s too. Tests
#: of the drive-side stop itself give host_timeout_ms explicitly.
IN_PROCESS_HOST_TIMEOUT_MS = 2000.0
#: The driver's consumer time of the simulated drives' heartbeats in those rigs, for the same
#: reason the other way round: with both cores kept busy by other processes the simulated drives
#: were seen silent for more than the default 350 ms, and the driver rightly took them for lost.
#: Tests of heartbeat loss itself give heartbeat_timeout_ms explicitly.
IN_PROCESS_HEARTBEAT_TIMEOUT_MS = 1000.0
#: A drive's data are stale after this many SYNC periods in the in-process rigs that judge freshness
#: (a trajectory's checks): the simulated drives, the driver and the test share one interpreter, and
#: a starved process found them 130 ms old (13 periods) at random. Tests of staleness wait for it.
IN_PROCESS_STALE_SYNCS = 50

#: How long a simulated drive's TPDOs may be unseen in those rigs before its data is late (the
#: verdict that refuses set-points and takes a wheel out): with both cores busy a whole bus's
#: TPDOs were seen 50-90 ms late, past the default five SYNC periods. Tests of late data itself
#: silence the TPDOs, which no bound outlasts.
IN_PROCESS_STALE_S = 0.3


def in_process_stale_after_syncs(sync_period_s: float) -> int:
    """``stale_after_syncs`` for IN_PROCESS_STALE_S at this SYNC period."""
    return max(5, round(IN_PROCESS_STALE_S / sync_period_s))


@pytest.fixture(autouse=True)
def _settled_heap() -> None:
    """Each test starts with the suite's heap settled (motor_driver.process.heap.settle), as every node and
    the simulator settle theirs once built. The suite's own process accumulates what hundreds of
    tests built; a full garbage collection then walked it all, stopping every thread for 110-190
    ms on an idle machine (a gc callback, mid-suite) and about twice that with both cores busy:
    an in-process driver's heartbeat went out 520 ms late and its drives, rightly, stopped by
    themselves (a loaded run, tests/test_ros_interface.py). Afterwards a collection walks only what
    the running test made."""
    heap.settle()


#: The command that runs the kernel tier (a real kernel's vcan0: natively, or in a small VM).
KERNEL_TIER_COMMAND = "./dev kernel-test"
#: Periods of the kernel tier's configs: in the VM (software emulation, Python about 12x slower)
#: behaviour is tested, not timing, so SYNC, host heartbeat and consumer times are generous. The
#: consumer times and the watchdog are above the worst stall measured in the VM beside the host
#: tier, with margin: a drive's consumer heard no host heartbeat for 1206 ms (a fresh clone's CI,
#: 1 s consumer times then); the session's worst stall is printed at its end (tests/kernel_stall.py).
#: The SDO timeout too: the simulator answers from a process of its own, which the VM holds as
#: long as it holds this one (a fresh clone's CI on a busy machine: a mode switch's SDO unanswered
#: within 2 s after the interface came back up).
KERNEL_BUS = {"sync_period_ms": 50, "host_heartbeat_ms": 100}
KERNEL_DRIVE = {"counts_per_rev": 4096, "heartbeat_period_ms": 200, "heartbeat_timeout_ms": 5000,
                "host_timeout_ms": 5000, "watchdog_ms": 5000, "sdo_timeout_ms": 5000}


def kernel_can_available(channel: str = "vcan0") -> str | None:
    """None when a kernel CAN interface can be opened, else the reason it cannot (and how)."""
    import socket

    how = f"; the kernel tier runs with `{KERNEL_TIER_COMMAND}` (natively where the kernel has vcan, else in a VM)"
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN" + how
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as err:
        return f"the kernel does not support AF_CAN ({err})" + how
    try:
        sock.bind((channel,))
    except OSError as err:
        return f"no {channel} interface ({err}); create it with: ip link add dev {channel} type vcan" + how
    finally:
        sock.close()
    return None


def kernel_controllers_available() -> str | None:
    """None when can0 and can1 are CAN controllers here (the kernel tier's VM: QEMU's emulated
    SJA1000 pair on one emulated bus), else why not."""
    if (why := kernel_can_available("vcan0")) is not None:
        return why
    try:
        from motor_driver.bus.link import read_kernel_health

        kinds = [read_kernel_health(name).kind for name in ("can0", "can1")]
    except Exception as err:
        return f"no CAN controllers can0 and can1 here ({err}); `{KERNEL_TIER_COMMAND}` runs a VM with an SJA1000 pair"
    if kinds != ["can", "can"]:
        return f"can0 and can1 are {kinds}, not CAN controllers; `{KERNEL_TIER_COMMAND}` runs a VM with an SJA1000 pair"
    return None


def make_config(n: int = 1, *, eds: str = "generic", bus_keys: dict[str, object] | None = None,
                **drive: object) -> RoverConfig:
    """``n`` drives (joint1.. on nodes 1..) on the simulator's socketcand bus can0, each with
    ``drive``'s keys over the in-process rigs' defaults; ``bus_keys``: more of the bus's."""
    drive.setdefault("host_timeout_ms", IN_PROCESS_HOST_TIMEOUT_MS)
    drive.setdefault("heartbeat_timeout_ms", IN_PROCESS_HEARTBEAT_TIMEOUT_MS)
    drive.setdefault("stale_after_syncs", in_process_stale_after_syncs(0.01))  # the bus's default SYNC period
    drives = [{"name": f"joint{i}", "node_id": i, "eds": eds, **drive} for i in range(1, n + 1)]
    return parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                    "kwargs": {"host": "127.0.0.1", "port": 1}, **(bus_keys or {})}],
                         "drives": drives}, source=REPO / "tests" / "generated.yaml")


@pytest.fixture
def default_config() -> RoverConfig:
    return load_config()


@pytest.fixture
def sim_factory() -> Iterator[Callable[[RoverConfig], tuple[SimService, RoverConfig]]]:
    started: list[SimService] = []

    def start(config: RoverConfig) -> tuple[SimService, RoverConfig]:
        sim = SimService.from_config(config, port=0)
        started.append(sim)
        return sim, with_bus_overrides(config, host=sim.host, port=sim.port)

    yield start
    for sim in started:
        sim.close()


@pytest.fixture
def driver_factory(sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]
                   ) -> Iterator[Callable[[RoverConfig], tuple[SimService, MotorDriver]]]:
    drivers: list[MotorDriver] = []

    def start(config: RoverConfig) -> tuple[SimService, MotorDriver]:
        sim, cfg = sim_factory(config)
        driver = MotorDriver(cfg)
        drivers.append(driver)
        driver.start()
        return sim, driver

    yield start
    for driver in drivers:
        driver.close()


#: The torque limit of :func:`torque_limited_drive`, and the refusal a command above it gets.
TORQUE_LIMIT_NM = 0.8
TORQUE_REFUSAL = r"max_torque_nm=0.8"


@pytest.fixture
def torque_limited_drive(driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> Drive:
    """joint1 of a one-drive rover with max_torque_nm=TORQUE_LIMIT_NM, enabled."""
    _, driver = driver_factory(make_config(1, max_torque_nm=TORQUE_LIMIT_NM))
    drive = driver.drive("joint1")
    drive.enable()
    return drive


@pytest.fixture
def listener_factory() -> Iterator[Callable[[SimService], can.BusABC]]:
    """An independent python-can socketcand client on the simulator's bus."""
    buses: list[can.BusABC] = []

    def open_bus(sim: SimService) -> can.BusABC:
        bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        buses.append(bus)
        # a passive client never ends the server's hold of its first frames early: wait it out
        # and take what it held, so that the listener sees the bus live from here on
        time.sleep(RAWMODE_HOLD_S + 0.02)
        drain(bus, 0.02)
        return bus

    yield open_bus
    for bus in buses:
        bus.shutdown()


def drain(bus: can.BusABC, seconds: float) -> list[can.Message]:
    out = []
    deadline = time.monotonic() + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(remaining)
        if msg is not None:
            out.append(msg)
    return out


#: A COB-ID no CANopen service of the simulated drives uses: the tests' marker frames.
MARKER_COB = 0x500
_markers = itertools.count(1)


def heard_before_marker(listener: can.BusABC, engine: BusEngine, channel: str = "can0",
                        timeout_s: float = 10.0) -> list[can.Message]:
    """Put a marker frame on ``channel`` from the bus itself and return every frame ``listener``
    heard before it: whatever the bus carried before the marker reached the listener too (one
    wire, one order), so an absence among them is heard, not waited for. Fails at the hang bound
    ``timeout_s`` naming the marker (is the listener listening?)."""
    token = next(_markers).to_bytes(4, "little")
    with VirtualBus(channel, engine=engine) as marker:
        marker.send(can.Message(arbitration_id=MARKER_COB, data=token, is_extended_id=False))
    heard: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while True:
        msg = listener.recv(max(0.0, deadline - time.monotonic()))
        if msg is None:
            raise AssertionError(f"marker {token.hex()} not heard in {timeout_s} s: is the listener listening?")
        if msg.arbitration_id == MARKER_COB and bytes(msg.data) == token:
            return heard
        heard.append(msg)


def on_the_bus(server: SocketcandServer, count: int, timeout_s: float = 10.0) -> None:
    """Wait until ``count`` clients of ``server`` are on its bus: the server replies to rawmode
    before it attaches the client, so a frame sent just after python-can's connect may find the
    client not yet there."""
    wait_for(lambda: sum(c.endpoint is not None for c in server.clients) == count, timeout_s,
             f"{count} clients on the bus")


def received_id(bus: can.BusABC, timeout_s: float) -> int | None:
    """The arbitration id of the next frame ``bus`` receives within ``timeout_s`` (a bound for a
    hang), or None if none came."""
    msg = bus.recv(timeout_s)
    return None if msg is None else msg.arbitration_id


def in_thread(call: Callable[[], object], catch: type[BaseException] = BaseException, *, name: str | None = None,
              start: bool = True) -> tuple[threading.Thread, list[BaseException]]:
    """``call`` on a thread of its own (started unless ``start`` is False); what it raises of
    ``catch`` lands in the list returned with the thread, anything else fails the thread."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            call()
        except catch as err:
            errors.append(err)

    thread = threading.Thread(target=run, name=name)
    if start:
        thread.start()
    return thread, errors


def ros_probe(name: str) -> tuple[Any, Any, Any]:
    """A fresh rclpy context, a node ``name`` in it and a single-threaded executor that spins
    only that node: (context, node, executor); the caller shuts them down."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rclpy.create_node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    return context, probe, executor


@contextmanager
def driver_node_spinning(driver: MotorDriver, *, probe_apart: bool = False) -> Iterator[Any]:
    """``driver`` behind a DriverNode on a hot 'events' executor, spinning, and a node 'probe' in
    the same fresh rclpy context, spun by that executor or (``probe_apart``) by one of its own;
    yields the probe. At the end the threads stop, the nodes go and the context shuts down (the
    driver is the caller's)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from nodes.joints.driver_node import DriverNode
    from nodes.process.spinning import SpinThread, make_executor

    context = rclpy.Context()
    rclpy.init(context=context)
    node = DriverNode(driver, context=context)
    probe = rclpy.create_node("probe", context=context)
    hot = make_executor("events", context)
    hot.add_node(node)
    spinning = [SpinThread(hot, "test-hot")]
    if probe_apart:
        probe_executor = SingleThreadedExecutor(context=context)
        probe_executor.add_node(probe)
        spinning.append(SpinThread(probe_executor, "test-probe"))
    else:
        hot.add_node(probe)
    try:
        yield probe
    finally:
        for spin in spinning:
            spin.stop(5.0)
        node.destroy_node()
        probe.destroy_node()
        rclpy.shutdown(context=context)


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str, said: Callable[[], str] | None = None) -> None:
    """Wait for ``predicate``; at the timeout fail naming ``what`` and, with ``said``, what the
    thing waited on said meanwhile (a subprocess's output)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}" + (f"; it said:\n{said()}" if said else ""))
        time.sleep(0.005)


def stop_reason(status: Any, ends: str) -> str | None:
    """The drive system's stop reason in a /diagnostics status when it ends with ``ends``, else
    None. health() says "stopped: <reason>" and, while odometry is not trusted, "; <why not>"
    after it: that tail must be the status's own "odometry" value (under load a wheel's first
    PDOs come late and odometry says so beside the stop)."""
    reason, found, after = status.message.partition(ends)
    odometry = next((kv.value for kv in status.values if kv.key == "odometry"), "")
    return reason + found if found and after in ("", f"; {odometry}") else None


def publish_until(publish: Callable[[], object], done: Callable[[], bool], timeout_s: float, what: str,
                  period_s: float = 0.05) -> None:
    """Publish a stream (every ``period_s``) until ``done``: its outcome, not a span of the wall
    clock (a crowded machine reaches it later); at the timeout fail naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s publishing until {what}")
        publish()
        time.sleep(period_s)


#: What a bench command's stderr says when its drive stopped itself because this host's heartbeat
#: went silent: a busy machine held the command's process past the drive's host timeout. The drive
#: did right; the test's premise (the process gets the CPU) did not hold.
HOST_SILENT = "EMCY 0x8130"


def rovercan_cli(*args: str, timeout: float = 60, stalls: int = 2) -> subprocess.CompletedProcess[str]:
    """`python -m rovercan ARGS` from the repository; run again (at most ``stalls`` times, said on
    stderr) when it failed only because it was held past its drive's host timeout. A command that
    never keeps its host heartbeat fails every time, so the test still fails."""
    for attempt in range(stalls + 1):
        result = subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                                timeout=timeout, check=False)
        if result.returncode == 0 or HOST_SILENT not in result.stderr or attempt == stalls:
            break
        warnings.warn(f"a stall, not a failure: `rovercan {' '.join(args)}` was held past its drive's host timeout"
                      f" (run {attempt + 1}); run once more", stacklevel=2)  # in pytest's warnings summary
    return result


@contextmanager
def rovercan_sim(*args: str) -> Iterator[int]:
    """`rovercan sim ARGS` in its own process on a free port, until the block ends; yields the port."""
    from .test_sim_cli import free_port

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", *args, "--port", str(port)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and "simulated drive" in proc.stdout.readline()
        yield port
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)


def stop_process(proc: subprocess.Popen[str], timeout_s: float = 30.0) -> None:
    """SIGTERM to ``proc``, and its end awaited with its pipes drained; killed if it has not ended
    within ``timeout_s`` (a bound for a hang: the whole suite loads two cores)."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


def realtime_allowed() -> bool:
    """This process may put a thread under SCHED_FIFO (root, CAP_SYS_NICE, an rtprio limit)."""
    result: list[bool] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))  # this short-lived thread only
            result.append(True)
        except OSError:
            result.append(False)
    thread = threading.Thread(target=attempt)
    thread.start()
    thread.join()
    return result[0]


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The kernel tier's worst stalls (tests/kernel_stall.py): what its consumer times must exceed."""
    from .kernel_stall import summary

    if line := summary():
        terminalreporter.write_line(line)


def enable_letting_go(drive: Drive, held: threading.Event) -> None:
    """Enable ``drive`` while ``held`` (the host heartbeats or guards a test holds back) stays set
    until the enable waits for the drive's host watch, then cleared: the enable must return only
    once the drive heard what was let go."""
    drive.channel.set_hook(lambda point: held.clear() if point == "enable: host watch" else None)
    try:
        drive.enable(timeout_s=30.0)  # a bound for a hang
    finally:
        drive.channel.set_hook(None)
        held.clear()


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

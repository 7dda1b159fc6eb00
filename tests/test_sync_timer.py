"""The SYNC of a socketcand bus comes from the daemon's timer (socketcand's broadcast manager,
'< add >'), not from a thread of the driver: a busy driver process does not shift it. A config
can ask for the thread; a second master's SYNC is still seen (by the rate)."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

import can

from can_config import RoverConfig, parse_config, with_bus_overrides
from motor_driver import MotorDriver
from motor_driver.bus.adapters import BATCH_READER_ATTRIBUTE, SOCKETCAND_SOCKET_ATTRIBUTE, SYNC_TEXT_BYTES
from motor_driver.bus.cyclic import DaemonCyclicTask, add_command
from virtual_can.service import SimService

from .conftest import IN_PROCESS_HOST_TIMEOUT_MS, REPO, drain, rovercan_sim, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def config(**bus: object) -> RoverConfig:
    return parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                    "kwargs": {"host": "127.0.0.1", "port": 1}, **bus}],
                         "drives": [{"name": "joint1", "node_id": 1, "host_timeout_ms": IN_PROCESS_HOST_TIMEOUT_MS,
                                     "sdo_timeout_ms": 2000}]},  # the simulator shares this test's CPU
                        source=REPO / "tests" / "generated.yaml")


def sync_times(listener: can.BusABC, seconds: float) -> list[float]:
    return [m.timestamp for m in drain(listener, seconds) if m.arbitration_id == 0x080]


def test_add_command_is_the_socketcand_line() -> None:
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    assert add_command(sync, 0.01) == "< add 0 10000 080 0 >"
    ext = can.Message(arbitration_id=0x1234567, data=b"\x01\xff", is_extended_id=True)
    assert add_command(ext, 2.5) == "< add 2 500000 01234567 2 01 FF >"


def held_interpreter_window(seconds: float) -> tuple[float, float]:
    """This interpreter held for ``seconds`` by one C call (the GIL is not given up inside it, as
    in a busy node's long call): no Python thread of this process runs meanwhile. Returns the
    window as wall times, the bus server's timestamp clock."""
    n = 3_000_000
    t0 = time.time()
    sum(range(n))
    per_item = (time.time() - t0) / n
    t0 = time.time()
    sum(range(int(seconds / max(per_item, 1e-10))))
    return t0, time.time()


def test_the_daemon_sends_the_sync_and_a_busy_driver_does_not_shift_it() -> None:
    """The simulator in a process of its own, the driver here: while this interpreter is held
    a SYNC thread of the driver cannot send; the daemon's timer does. Judged by order (SYNCs the
    server stamped inside the held window), not by how evenly they came: that is a benchmark's."""
    with rovercan_sim("--drives", "1") as port:
        cfg = with_bus_overrides(config(), port=port)
        with MotorDriver(cfg) as driver:
            driver.start()
            assert isinstance(driver.buses["can0"].sync_task, DaemonCyclicTask)
            listener = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
            try:
                drain(listener, 0.1)
                inside = 0
                for seconds in (0.3, 1.0, 3.0):  # longer windows only for a machine that starves the server
                    t0, t1 = held_interpreter_window(seconds)
                    quarter = (t1 - t0) / 4  # a thread's catch-up burst lands at the window's edges: its middle only
                    inside = len([t for t in sync_times(listener, 0.2) if t0 + quarter < t < t1 - quarter])
                    if inside >= 2:
                        break
            finally:
                listener.shutdown()
            assert inside >= 2, f"{inside} SYNC sent while the driver's interpreter was held: the SYNC needs its thread"
            assert driver.drive("joint1").watch.foreign_master == ""  # its own SYNC, reaching it, is not another master's


def test_a_config_can_keep_the_sync_in_a_thread(driver_factory: DriverFactory,
                                                listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(config(sync_timer="thread"))
    task = driver.buses["can0"].sync_task
    assert task is not None and not isinstance(task, DaemonCyclicTask)
    assert isinstance(task, can.broadcastmanager.CyclicSendTaskABC) and task.period == 0.01
    listener = listener_factory(sim)
    seen: list[float] = []
    wait_for(lambda: bool(seen.extend(sync_times(listener, 0.05))) or len(seen) >= 5, 30.0, "five SYNC from the thread")


def test_the_sync_echo_is_held_back_only_while_the_daemon_sends_the_sync(driver_factory: DriverFactory) -> None:
    """adapters.hold_lone_sync: set with the daemon's SYNC job, cleared when the job stops (no
    SYNC would then push a frame without data through) and never set with the thread's SYNC.
    The mark is asked of the bus's batch reader, and its receive thread (the socket mark's one
    writer) sets it before its next wait: the socket's mark is waited for, within that wait's
    timeout (the notifier's, 0.1 s) or the next frame."""
    def mark(driver: MotorDriver) -> int:
        sock = getattr(driver.buses["can0"].bus, SOCKETCAND_SOCKET_ATTRIBUTE)
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT))

    def becomes(driver: MotorDriver, value: int) -> None:
        wait_for(lambda: mark(driver) == value, 30.0, f"the receive mark {value}", lambda: str(mark(driver)))

    _, driver = driver_factory(config())
    handle = driver.buses["can0"]
    assert isinstance(handle.sync_task, DaemonCyclicTask)
    becomes(driver, SYNC_TEXT_BYTES + 1)
    handle.stop_sync()
    becomes(driver, 1)
    handle.restart_sync()
    becomes(driver, SYNC_TEXT_BYTES + 1)
    _, threaded = driver_factory(config(sync_timer="thread"))
    reader = getattr(threaded.buses["can0"].bus, BATCH_READER_ATTRIBUTE)
    assert reader.hold_mark == 1 and mark(threaded) == 1  # never asked for

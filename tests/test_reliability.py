"""Reliability: bus loss and return, frame faults at 1 % and 10 %, random frames at the driver,
no thread or socket leaks."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config import RoverConfig, with_bus_overrides
from can_config.errors import MotorError
from motor_driver import MotorDriver, State
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def settled_threads() -> int:
    """The thread count once it holds still for 0.3 s: a server thread of a client that just
    left (the driver's retried handshake, a listener) ends within its poll period."""
    history = [threading.active_count()]
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and (len(history) < 6 or len(set(history[-6:])) > 1):
        time.sleep(0.05)
        history.append(threading.active_count())
    return history[-1]


def test_bus_server_dies_driver_reports_reconnects_reconfigures_no_leaks(
        sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
    sim, cfg = sim_factory(make_config(2))
    port = sim.port
    threads0, fds0 = settled_threads(), open_fds()
    driver = MotorDriver(cfg).start()
    for drive in driver:
        drive.enable()
    threads1, fds1 = settled_threads(), open_fds()
    boots = [d.boot_count for d in driver]
    sim.close()  # the bus server dies
    wait_for(lambda: driver.bus_lost["can0"], 2.0, "bus reported lost")
    drive = driver.drive("joint1")
    assert drive.snapshot().lost and drive.snapshot().fault
    with pytest.raises(MotorError):
        drive.move_to(10.0)  # no motion commanded while the bus is gone
    time.sleep(1.0)  # a few reconnect attempts with back-off
    second = SimService.from_config(make_config(2), port=port)  # the bus returns
    try:
        wait_for(lambda: not driver.bus_lost["can0"], 10.0, "bus re-established")
        assert [d.boot_count for d in driver] == [b + 1 for b in boots]  # configured again ...
        assert all(d.state is State.SWITCH_ON_DISABLED for d in driver)  # ... but not re-armed
        with pytest.raises(MotorError):
            drive.move_to(10.0)
        drive.enable()
        drive.move_to(10.0, wait=True)
        assert (settled_threads(), open_fds()) == (threads1, fds1)  # nothing leaked by the reconnect
        driver.close()
        assert (settled_threads(), open_fds()) == (threads0, fds0)  # nothing left after close
    finally:
        driver.close()
        second.close()


@pytest.mark.parametrize("rate", [0.01, 0.10])
def test_frame_faults_no_crash_no_wrong_state(driver_factory: DriverFactory, rate: float) -> None:
    sim, driver = driver_factory(make_config(2))
    for drive in driver:
        drive.enable()
    apply_action(sim, {"action": "frames", "drop": rate, "delay": rate, "delay_s": 0.003, "corrupt": rate})
    end = time.monotonic() + 2.0
    k = 0
    while time.monotonic() < end:
        k += 1
        for drive in driver:
            try:
                drive.move_to((k * 7) % 90)
            except MotorError:
                pass  # refused while a drive is (wrongly or rightly) seen as lost: never a crash
        for state in driver.states():
            assert isinstance(state.state, State) and -1e6 < state.angle_deg < 1e6
        time.sleep(0.05)
    apply_action(sim, {"action": "frames", "drop": 0.0, "delay": 0.0, "corrupt": 0.0})
    time.sleep(0.5)
    for drive in driver:
        simulated = sim.simulator_for(drive.node_id).call(
            lambda d=drive: sim.simulator_for(d.node_id).drive(d.node_id).position_counts)
        # what the driver reports is what the drive has (within one SYNC of motion)
        assert drive.position_counts == pytest.approx(simulated, abs=50)
    assert driver._supervisor is not None and driver._supervisor.is_alive()
    assert all(h.network.notifier is not None and h.network.notifier.exception is None for h in driver.buses.values())


def test_corrupted_position_is_not_reported(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    network = driver.buses["can0"].network
    seq = drive._position_seq
    wait_for(lambda: drive._position_seq > seq + 1, 1.0, "position TPDOs")
    before = drive.position_counts
    t = time.time()
    network.notify(0x281, bytearray((before + 2**20).to_bytes(4, "little", signed=True) + bytes(4)), t)
    assert drive.position_counts == before  # a one-off jump beyond max velocity is held back
    assert drive.implausible_samples == 1


FRAME = st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8))


@pytest.fixture
def one_driver(driver_factory: DriverFactory) -> MotorDriver:
    return driver_factory(make_config(1))[1]


@settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", "250")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.lists(FRAME, min_size=40, max_size=40))
def test_random_frames_never_crash_the_driver(one_driver: MotorDriver, frames: list[tuple[int, bytes]]) -> None:
    """250 examples x 40 frames = 10,000 random frames into the driver's receive path (the
    canopen network's dispatch, as the receive thread calls it)."""
    driver = one_driver
    network = driver.buses["can0"].network
    for cob, data in frames:
        network.notify(cob, bytearray(data), time.time())  # raises if any callback does
    time.sleep(0.005)  # let the driver's own threads run between bursts
    drive = driver.drive("joint1")
    assert 0 <= drive.statusword <= 0xFFFF and isinstance(drive.state, State)
    assert -(2**31) <= drive.position_counts < 2**31


def test_driver_opens_a_bus_whose_first_handshake_is_garbled() -> None:
    """A socketcand daemon sends frames as soon as it answers rawmode, so its '< ok >' can reach
    python-can's handshake read together with a frame, which fails the connect. The driver
    tries again (a scripted daemon: the first connection coalesces, the second does not)."""
    daemon = socket.create_server(("127.0.0.1", 0))
    daemon.settimeout(5.0)
    accepted: list[socket.socket] = []

    def serve() -> None:
        for garbled in (True, False):
            conn, _ = daemon.accept()
            accepted.append(conn)
            conn.sendall(b"< hi >")
            conn.recv(256)  # < open can0 >
            conn.sendall(b"< ok >")
            conn.recv(256)  # < rawmode >
            conn.sendall(b"< ok >< frame 701 0.000000 7F >" if garbled else b"< ok >")

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    cfg = with_bus_overrides(make_config(1), host="127.0.0.1", port=daemon.getsockname()[1])
    try:
        with MotorDriver(cfg) as driver:
            assert len(accepted) == 2  # one garbled handshake, one retry
            assert not driver.bus_lost["can0"]
    finally:
        server.join(2.0)
        for conn in accepted:
            conn.close()
        daemon.close()

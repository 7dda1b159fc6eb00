"""Reliability: bus loss and return, frame faults at 1 % and 10 %, random frames at the driver,
no thread or socket leaks."""

from __future__ import annotations

import dataclasses
import os
import socket
import threading
import time
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config import RoverConfig, with_bus_overrides
from can_config.errors import BusLostError, MotorError
from motor_driver import Drive, MotorDriver, State
from motor_driver.bus.handle import RECONNECT_MIN_S
from motor_driver.runtime.driver import HANDSHAKE_TIMEOUT_S, OPEN_ATTEMPTS
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for
from .drive_states import fault, lost

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def settled_fds(limit: int) -> int:
    """Open descriptors, given up to 2 s to come down to ``limit`` (a file being written closes)."""
    deadline = time.monotonic() + 2.0
    while open_fds() > limit and time.monotonic() < deadline:
        time.sleep(0.05)
    return open_fds()


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
    boots = [d.boot.boot_count for d in driver]
    sim.close()  # the bus server dies
    wait_for(lambda: driver.bus_lost["can0"], 2.0, "bus reported lost")
    drive = driver.drive("joint1")
    assert lost(drive.snapshot()) and fault(drive.snapshot())
    with pytest.raises(MotorError):
        drive.move_to(10.0)  # no motion commanded while the bus is gone
    record = driver.supervisor.bus.bus_records["can0"]  # a few reconnect attempts, each doubling the back-off
    wait_for(lambda: record.backoff_s >= 4 * RECONNECT_MIN_S, 30.0, "two failed reconnect attempts")
    second = SimService.from_config(make_config(2), port=port)  # the bus returns
    try:
        wait_for(lambda: not driver.bus_lost["can0"], 10.0, "bus re-established")
        assert [d.boot.boot_count for d in driver] == [b + 1 for b in boots]  # configured again ...
        assert all(d.cache.state is State.SWITCH_ON_DISABLED for d in driver)  # ... but not re-armed
        with pytest.raises(MotorError):
            drive.move_to(10.0)
        drive.enable()
        drive.move_to(10.0, wait=True)
        # nothing leaked by the reconnect, nothing left after close (descriptors: at most as many;
        # a file the flight recorder writes meanwhile comes and goes)
        assert settled_threads() == threads1 and settled_fds(fds1) <= fds1
        driver.close()
        assert settled_threads() == threads0 and settled_fds(fds0) <= fds0
    finally:
        driver.close()
        second.close()


def test_a_heartbeat_received_after_the_bus_was_lost_does_not_bring_the_drive_back(
        driver_factory: DriverFactory) -> None:
    """The receive thread can still hold a heartbeat when the supervisor marks the bus's drives
    lost (seen on a loaded machine: MotorState never said LOST). Here the bus stays up, so every
    heartbeat after the mark is such a late one: the drive stays lost until it is booted again."""
    _sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    supervisor = driver.supervisor
    supervisor.call(lambda: supervisor._drive_gone(drive))  # what it does to each drive of a lost bus
    beats = drive.cache.last_heartbeat
    wait_for(lambda: drive.cache.last_heartbeat > beats + 0.05, 3.0, "two more heartbeats of the drive")
    assert lost(drive.snapshot()) and fault(drive.snapshot())
    with pytest.raises(MotorError):
        drive.move_to(10.0)
    drive.boot.boot()  # what the reconnect does once the bus is back
    assert not lost(drive.snapshot())


@pytest.mark.parametrize("rate", [0.01, 0.10])
def test_frame_faults_no_crash_no_wrong_state(driver_factory: DriverFactory, rate: float) -> None:
    sim, driver = driver_factory(make_config(2))
    for drive in driver:
        drive.enable()
    apply_action(sim, {"action": "frames", "drop": rate, "delay": rate, "delay_s": 0.003, "corrupt": rate})
    for k in range(1, 41):  # 40 rounds of commands under the faults (a count: a starved run does them all)
        for drive in driver:
            try:
                drive.move_to((k * 7) % 90)
            except MotorError:
                pass  # refused while a drive is (wrongly or rightly) seen as lost: never a crash
        for state in driver.states():
            assert isinstance(state.state, State) and -1e6 < state.angle_deg < 1e6
        time.sleep(0.05)
    apply_action(sim, {"action": "frames", "drop": 0.0, "delay": 0.0, "corrupt": 0.0})
    for drive in driver:
        def simulated(d: Drive = drive) -> object:
            runner = sim.simulator_for(d.node_id)
            return runner.call(lambda: runner.drive(d.node_id).position_counts)

        # what the driver reports comes to be what the drive has (within one SYNC of motion) once
        # the delayed frames are in: a wrong state that stays fails at the hang bound
        wait_for(lambda d=drive: d.cache.received.position_counts == pytest.approx(simulated(d), abs=50), 10.0,  # type: ignore[misc]
                 f"{drive.name}'s reported position at the drive's")
    assert not driver.supervisor.dead
    assert all(h.network.notifier is not None and h.network.notifier.exception is None for h in driver.buses.values())


def _position_receiving(driver_factory: DriverFactory) -> tuple[Drive, Callable[[int, float], None]]:
    """One drive whose position TPDOs arrive, and a way to feed it a position sample (as its
    receive thread would) stamped at a given time."""
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    network = driver.buses["can0"].network
    seq = drive.cache.position_seq
    wait_for(lambda: drive.cache.position_seq > seq + 1, 1.0, "position TPDOs")

    def feed(counts: int, t: float) -> None:
        network.notify(0x281, bytearray(counts.to_bytes(4, "little", signed=True) + bytes(4)), t)
    return drive, feed


def test_corrupted_position_is_not_reported(driver_factory: DriverFactory) -> None:
    drive, feed = _position_receiving(driver_factory)
    before = drive.cache.received.position_counts
    feed(before + 2**20, time.time())
    assert drive.cache.received.position_counts == before  # a one-off jump beyond max velocity is held back
    assert drive.cache.positions.implausible == 1


def test_a_jump_is_taken_only_when_two_more_samples_agree(driver_factory: DriverFactory) -> None:
    """The same corruption twice in a row is still held back; a real jump (homing, a reboot)
    is taken with the third sample that agrees."""
    drive, feed = _position_receiving(driver_factory)
    before = drive.cache.received.position_counts
    jumped = before + 2**29
    t = time.time()
    for i, expected in enumerate((before, before, jumped)):
        feed(jumped, t + 0.001 * i)
        assert drive.cache.received.position_counts == expected, f"after {i + 1} sample(s) of the jump"


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
    assert 0 <= drive.cache.received.statusword <= 0xFFFF and isinstance(drive.cache.state, State)
    assert -(2**31) <= drive.cache.received.position_counts < 2**31


class ScriptedDaemon:
    """A socketcand server that follows a script per connection: the driver's greeting probe
    (it reads '< hi >' and leaves) is answered and not counted; each later connection gets the
    next handshake from ``script``: 'garbled' (the rawmode '< ok >' arrives with a frame), 'ok'
    or 'mute' (greets, then never answers '< open >')."""

    def __init__(self, script: list[str]) -> None:
        self.script = script
        self.handshakes: list[str] = []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(10.0)
        self.port = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            while len(self.handshakes) < len(self.script):
                conn, _ = self.sock.accept()
                self.conns.append(conn)
                conn.sendall(b"< hi >")
                if not conn.recv(256):  # < open can0 >, or the probe leaving
                    continue
                kind = self.script[len(self.handshakes)]
                self.handshakes.append(kind)
                if kind == "mute":
                    continue
                conn.sendall(b"< ok >")
                conn.recv(256)  # < rawmode >
                conn.sendall(b"< ok >< frame 701 0.000000 7F >" if kind == "garbled" else b"< ok >")
        except OSError:
            pass  # closed by close()

    def close(self) -> None:
        self.sock.close()
        for conn in self.conns:
            conn.close()
        self.thread.join(2.0)


def test_driver_opens_a_bus_whose_first_handshake_is_garbled() -> None:
    """A socketcand daemon sends frames as soon as it answers rawmode, so its '< ok >' can reach
    python-can's handshake read together with a frame, which fails the connect. The driver
    tries again (a scripted daemon: the first handshake coalesces, the second does not)."""
    daemon = ScriptedDaemon(["garbled", "ok"])
    cfg = with_bus_overrides(make_config(1), host="127.0.0.1", port=daemon.port)
    try:
        with MotorDriver(cfg) as driver:
            assert daemon.handshakes == ["garbled", "ok"]  # one garbled handshake, one retry
            assert not driver.bus_lost["can0"]
    finally:
        daemon.close()


def test_a_port_that_accepts_but_never_greets_is_named_not_waited_on_for_ever() -> None:
    """python-can's handshake reads without a timeout: a port that accepts and stays silent
    (another service, a hung daemon) would hang the driver. It is an error naming host:port."""
    silent = socket.create_server(("127.0.0.1", 0))
    port = silent.getsockname()[1]
    cfg = with_bus_overrides(make_config(1), host="127.0.0.1", port=port)
    cfg = dataclasses.replace(cfg, buses=tuple(dataclasses.replace(b, connect_timeout_s=1.0) for b in cfg.buses))
    try:
        start = time.monotonic()
        with pytest.raises(BusLostError, match=rf"127.0.0.1:{port} no socketcand server \(it accepted but sent no socketcand"
                                               r" greeting.*are host and port right"):
            MotorDriver(cfg)
        assert time.monotonic() - start < 3 * HANDSHAKE_TIMEOUT_S
    finally:
        silent.close()


def test_a_server_that_greets_then_stops_answering_is_given_up_with_a_clear_error() -> None:
    daemon = ScriptedDaemon(["mute"] * OPEN_ATTEMPTS)
    cfg = with_bus_overrides(make_config(1), host="127.0.0.1", port=daemon.port)
    try:
        with pytest.raises(BusLostError, match=r"handshake did not finish within .* stopped answering"):
            MotorDriver(cfg)
        assert daemon.handshakes == ["mute"]  # a timeout is not retried: the server is hung
    finally:
        daemon.close()

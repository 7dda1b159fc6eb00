"""Background work is supervised: an exception nobody foresaw (``Boom``, of no type the code
lists) forced into each background job of the driver (a bus's reconnect, a drive's
re-configuration, the supervisor's period, a receive callback) is logged with its cause, counted,
and ends in a retry or a stop, and the driver's status for /diagnostics says so
(:func:`motor_driver.diagnostics.health.jobs_health`, :func:`motor_driver.diagnostics.health.drive_health`). The driver
runs on the simulator over socketcand; each verdict waits for an outcome (a hang bound, no clock)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import can
import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from motor_driver.diagnostics.health import ERROR, WARN, Rejections, drive_health
from motor_driver.runtime import supervise_bus as supervise_bus_module
from motor_driver.runtime.supervisor import SUPERVISOR_FAILURES_MAX
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for
from .drive_states import stale

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


class Boom(Exception):
    """An exception of a type no code of the driver names."""


def failing(times: int, real: Callable[..., Any]) -> tuple[Callable[..., Any], list[int]]:
    """``real``, raising Boom on its first ``times`` calls; the list counts the calls."""
    calls: list[int] = []

    def call(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) <= times:
            raise Boom(f"forced failure {len(calls)}")
        return real(*args, **kwargs)

    return call, calls


def boom_lines(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.levelno >= logging.WARNING and "Boom" in r.getMessage()]


def sim_state(sim: SimService, node: int = 1) -> str:
    runner = sim.simulators["can0"]
    return str(runner.call(lambda: runner.drive(node).state.name))


def test_a_reconnect_that_raises_anything_is_logged_counted_and_tried_again(
        driver_factory: DriverFactory, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    sim, driver = driver_factory(make_config(1))
    opening, calls = failing(2, supervise_bus_module.open_bus)
    monkeypatch.setattr(supervise_bus_module, "open_bus", opening)
    apply_action(sim, {"action": "disconnect_clients"})
    wait_for(lambda: driver.bus_lost["can0"], 10.0, "the bus lost")
    wait_for(lambda: len(calls) >= 3 and not driver.bus_lost["can0"], 30.0,
             "the bus back after two tries that raised")
    fault = driver.supervisor.faults.snapshot()["reconnect"]
    assert fault.count == 2 and "Boom: forced failure 2" in fault.cause and fault.where == "bus can0"
    health = driver.jobs_health()
    assert health.level == WARN and "Boom" in health.message and health.values["reconnect"] == "2"
    lines = [r for r in boom_lines(caplog) if r.name == "motor_driver.process.jobs"]
    assert len(lines) == 1 and lines[0].levelno == logging.ERROR and lines[0].exc_info is not None  # its traceback
    assert any("next try in" in r.getMessage() for r in boom_lines(caplog))  # each try said with its back-off


def test_a_reconfiguration_that_raises_anything_is_tried_again(
        driver_factory: DriverFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    boots = drive.boot.boot_count
    reconfigure, calls = failing(1, drive.boot.reconfigure)
    monkeypatch.setattr(drive.boot, "reconfigure", reconfigure)
    apply_action(sim, {"action": "power_cycle", "node": 1})
    wait_for(lambda: len(calls) >= 2 and drive.cache.booted and drive.boot.boot_count > boots, 30.0,
             "the drive configured again after a try that raised")
    fault = driver.supervisor.faults.snapshot()["reconfigure"]
    assert fault.count == 1 and fault.where == "joint1" and "Boom" in fault.cause
    assert driver.jobs_health().values["reconfigure"] == "1"


def heard(bus: can.BusABC, match: Callable[[can.Message], bool], what: str) -> None:
    """Wait (a hang bound) for a frame on ``bus`` that ``match``es."""
    wait_for(lambda: (msg := bus.recv(0.1)) is not None and match(msg), 10.0, what)


def test_one_failed_supervisor_period_is_passed_over_repeated_ones_stop_every_drive(
        driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC],
        monkeypatch: pytest.MonkeyPatch) -> None:
    sim, driver = driver_factory(make_config(2))
    supervisor = driver.supervisor
    handle = driver.buses["can0"]
    beat, calls = failing(1, supervisor.bus.beat)
    monkeypatch.setattr(supervisor.bus, "beat", beat)
    wait_for(lambda: len(calls) >= 2, 10.0, "a period after the one that raised")
    beats = handle.host_beats
    wait_for(lambda: handle.host_beats > beats + 2, 10.0, "host heartbeats going on")
    assert not supervisor.dead and supervisor.faults.snapshot()["supervisor"].count == 1
    assert driver.jobs_health().level == WARN
    for drive in driver:
        drive.enable()
    assert sim_state(sim, 1) == "OPERATION_ENABLED"

    def always(now: float) -> None:
        raise Boom("every period")

    listener = listener_factory(sim)
    monkeypatch.setattr(supervisor.bus, "beat", always)
    for node in (1, 2):  # told to stop through each drive's command channel (its RPDO: quick stop)
        heard(listener, lambda m, node=node: m.arbitration_id == 0x200 + node and m.data[0] == 0x02,
              f"the quick stop of drive {node}")
    wait_for(lambda: supervisor.dead, 10.0, "the supervisor's loop ended")
    assert supervisor.faults.snapshot()["supervisor"].count == 1 + SUPERVISOR_FAILURES_MAX
    health = driver.jobs_health()
    assert health.level == ERROR and "Boom: every period" in health.message and "told to stop" in health.message
    for node in (1, 2):
        wait_for(lambda node=node: sim_state(sim, node) != "OPERATION_ENABLED", 10.0, f"drive {node} stopped")


def test_frames_a_receive_callback_raises_on_are_counted_said_and_do_not_read_as_a_stalled_bus(
        driver_factory: DriverFactory, caplog: pytest.LogCaptureFixture) -> None:
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    network = driver.buses["can0"].network
    decode = drive.cache.on_tpdo

    def broken_decoding(cob_id: int, data: bytearray, timestamp: float) -> None:
        raise Boom(f"cannot decode 0x{cob_id:03X}")

    for cob in [c for c, callbacks in network.subscribers.items() if decode in callbacks]:
        network.unsubscribe(cob, decode)
        network.subscribe(cob, broken_decoding)
    wait_for(lambda: stale(drive.snapshot()) and rejected_count(driver) > 10, 10.0,
             "its TPDOs rejected until its data is stale")
    rejected = driver.rejected(drive)
    assert rejected is not None and "broken_decoding: Boom: cannot decode 0x" in rejected.cause
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s,
                          rejected=Rejections(rejected.count, rejected.cause, 0.0))
    assert health.level == ERROR and "rejected by the driver" in health.message and "Boom" in health.message
    assert "bus or this host is stalled" not in health.message
    assert health.values["rejected_frames"] == str(rejected.count)
    assert len(boom_lines(caplog)) == 1  # every rejection counted, one line logged with its cause


def rejected_count(driver: MotorDriver) -> int:
    rejected = driver.rejected(driver.drive("joint1"))
    return 0 if rejected is None else rejected.count


def test_diagnostics_say_a_failed_job_and_rejected_frames(driver_factory: DriverFactory,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray

    from nodes.process.qos import DIAGNOSTICS_QOS

    from .conftest import driver_node_spinning

    sim, driver = driver_factory(make_config(1))
    network = driver.buses["can0"].network

    def broken_decoding(cob_id: int, data: bytearray, timestamp: float) -> None:
        raise Boom("cannot decode")

    network.subscribe(0x701, broken_decoding)  # beside the drive's own: its heartbeats still count
    wait_for(lambda: rejected_count(driver) > 0, 10.0, "a heartbeat rejected")
    opening, _ = failing(1_000_000, supervise_bus_module.open_bus)
    monkeypatch.setattr(supervise_bus_module, "open_bus", opening)
    apply_action(sim, {"action": "disconnect_clients"})
    seen: list[Any] = []
    with driver_node_spinning(driver) as probe:
        probe.create_subscription(DiagnosticArray, "/diagnostics", seen.append, DIAGNOSTICS_QOS)

        def said(name: str, key: str) -> bool:
            return any(s.name == name and s.level >= bytes([WARN]) and "Boom" in s.message + str(s.values)
                       and any(kv.key == key and kv.value != "0" for kv in s.values)
                       for array in seen for s in array.status)

        wait_for(lambda: said("rovercan: driver", "reconnect"), 30.0, "the failed reconnect on /diagnostics")
        wait_for(lambda: said("rovercan: joint1", "rejected_frames"), 30.0, "the rejected frames on /diagnostics")

"""A drive that resets itself in the middle of its configuration is never enabled with anything but
the configuration asked: the simulated peer resets (objects back to their EDS values, boot-up) at
the k-th SDO write of the driver's configuration, k drawn over the whole of it, and again in the
configuration that follows; after enable, the PDO objects are read back from outside (the
simulated drive's own object dictionary, on its thread) and must be what a clean boot leaves.

Also: a reset at the first write of 0x1600 is not called booted before the configuration is in
place and a statusword decoded; an arbitrary exception in a re-configuration is logged once,
counted, retried, and the drive ends configured."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config import RoverConfig
from can_config.errors import BootError, ConfigError
from motor_driver import MotorDriver
from motor_driver.drive import Drive
from motor_driver.drive.ledger import DriveRecord
from motor_driver.drive.setup.boot import configuration_stamp
from motor_driver.protocol.cia402 import State
from motor_driver.protocol.pdo import mapping_writes
from virtual_can import SimService
from virtual_can.scenario import apply_action
from virtual_can.sim.drive.model import State as SimState

from .conftest import SHARED_EDS, make_config, requires_shared, wait_for

HANG_S = 30.0  # a bound for a hang, not a timing claim
NODE = 1

Objects = dict[tuple[int, int], object]
Factory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def pdo_objects(sim: SimService) -> Objects:
    """Every PDO communication and mapping object the simulated drive holds, read on its thread."""
    simulator = sim.simulator_for(NODE)
    drive = simulator.drive(NODE)

    def read() -> Objects:
        return {key: value for key, value in drive.store.values.items() if 0x1400 <= key[0] <= 0x1BFF}

    objects = simulator.call(read)
    assert isinstance(objects, dict)
    return objects


def sim_state(sim: SimService) -> SimState:
    simulator = sim.simulator_for(NODE)
    state = simulator.call(lambda: simulator.drive(NODE).state)
    assert isinstance(state, SimState)
    return state


def assert_asked(objects: Objects) -> None:
    """What the driver asks of the generic EDS's drive, written down here on its own: RPDO1-4 at
    0x201-0x501 (controlword; + target position, velocity, torque), TPDO1 statusword + mode."""
    assert [objects[(0x1400 + n, 1)] for n in range(4)] == [0x201, 0x301, 0x401, 0x501]
    assert [objects[(0x1601, sub)] for sub in range(3)] == [2, 0x60400010, 0x607A0020]
    assert [objects[(0x1602, sub)] for sub in range(3)] == [2, 0x60400010, 0x60FF0020]
    assert [objects[(0x1A00, sub)] for sub in range(3)] == [2, 0x60410010, 0x60610008]


def assert_enabled_as_asked(sim: SimService, drive: Drive) -> None:
    """The drive enables, holding the configuration asked."""
    drive.enable()
    assert sim_state(sim) is SimState.OPERATION_ENABLED
    assert_asked(pdo_objects(sim))


def one_drive(driver_factory: Factory) -> tuple[SimService, Drive, DriveRecord]:
    """One drive booted, and what the supervisor keeps of it."""
    sim, driver = driver_factory(make_config(1))
    return sim, driver.drive("joint1"), driver.supervisor.records["joint1"]


@contextmanager
def hooked(drive: Drive, hook: Callable[[str], None]) -> Iterator[int]:
    """``hook`` in the drive's command channel while the block runs; yields the boot count before it."""
    drive.channel.set_hook(hook)
    try:
        yield drive.boot.boot_count
    finally:
        drive.channel.set_hook(None)


@pytest.fixture
def rig(driver_factory: Factory, listener_factory: Callable[[SimService], can.BusABC]
        ) -> Iterator[tuple[SimService, MotorDriver, Objects, int]]:
    """One drive booted; the PDO objects a clean boot leaves; the SDO writes of one clean
    re-configuration, counted on the bus by an independent listener."""
    sim, driver = driver_factory(make_config(1))
    reference = pdo_objects(sim)
    assert_asked(reference)
    listener = listener_factory(sim)
    drive = driver.drive("joint1")
    boots = drive.boot.boot_count
    apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.05})
    writes = 0
    while True:  # every request up to the NMT start that ends the configuration
        msg = listener.recv(HANG_S)
        assert msg is not None, "no NMT start within the hang bound"
        if msg.arbitration_id == 0x600 + NODE and msg.data[0] >> 5 == 1:  # initiate download
            writes += 1
        if msg.arbitration_id == 0 and bytes(msg.data) == bytes([1, NODE]):
            break
    wait_for(lambda: drive.boot.boot_count > boots and drive.cache.booted, HANG_S, "a clean re-configuration")
    assert writes > 30  # the PDO set alone is more
    yield sim, driver, reference, writes


def configure_with_resets(sim: SimService, driver: MotorDriver, at_writes: list[int], answer: bool) -> Drive:
    """Power-cycle the drive with resets armed at ``at_writes``; return it once booted again."""
    drive = driver.drive("joint1")
    boots = drive.boot.boot_count
    apply_action(sim, {"action": "sdo_reset", "node": NODE, "at_writes": at_writes, "answer": answer})
    apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.05})
    wait_for(lambda: drive.boot.boot_count > boots and drive.cache.booted, HANG_S, "the drive configured again")
    apply_action(sim, {"action": "sdo_reset", "node": NODE})  # what was not used up goes
    return drive


@settings(max_examples=12, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_a_drive_reset_at_any_write_of_its_configuration_is_enabled_only_as_configured(
        rig: tuple[SimService, MotorDriver, Objects, int], data: st.DataObject) -> None:
    sim, driver, reference, writes = rig
    first = data.draw(st.integers(1, writes), label="reset at write")
    again = data.draw(st.integers(1, writes + 1), label="and at write (of the next configuration)")
    answer = data.draw(st.booleans(), label="the write that resets it is answered")
    record = driver.supervisor.records["joint1"]
    restarts = getattr(record, "boot_restarts", 0)
    drive = configure_with_resets(sim, driver, [first, again], answer)
    drive.enable()
    assert sim_state(sim) is SimState.OPERATION_ENABLED
    assert pdo_objects(sim) == reference
    drive.disable()
    assert record.boot_restarts > restarts  # said where /diagnostics reads it
    assert "boot-up" in record.boot_restart_why


def test_a_reset_at_the_first_write_of_0x1600_is_not_booted_before_it_is_configured(
        sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]],
        caplog: pytest.LogCaptureFixture) -> None:
    """Each time the driver says "booted", the drive holds the configuration asked (read from the
    simulated drive's own objects at that moment, on the booting thread) and its statusword
    decodes; the reset is counted."""
    sim, cfg = sim_factory(make_config(1))
    apply_action(sim, {"action": "sdo_reset", "node": NODE, "index": 0x1600, "subindex": 0})
    held_when_booted: list[Objects] = []
    states_when_booted: list[State] = []
    driver = MotorDriver(cfg)

    class AtBooted(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.getMessage().startswith(f"node {NODE} (joint1) booted"):
                held_when_booted.append(pdo_objects(sim))
                states_when_booted.append(driver.drive("joint1").cache.state)

    hook = AtBooted()
    logging.getLogger("motor_driver.drive.setup.boot").addHandler(hook)
    caplog.set_level(logging.INFO, logger="motor_driver")
    try:
        with driver:
            driver.start()
            drive = driver.drive("joint1")
            record = driver.supervisor.records["joint1"]
            assert record.boot_restarts == 1 and "boot-up" in record.boot_restart_why
            assert "configuring it again from the start" in caplog.text
            assert len(held_when_booted) == 1
            assert_asked(held_when_booted[0])
            assert states_when_booted[0] is not State.UNKNOWN
            assert_enabled_as_asked(sim, drive)
    finally:
        logging.getLogger("motor_driver.drive.setup.boot").removeHandler(hook)


def test_a_drive_that_keeps_resetting_is_a_boot_error_naming_it(
        sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
    sim, cfg = sim_factory(make_config(1))
    apply_action(sim, {"action": "sdo_reset", "node": NODE, "at_writes": [5] * 40})
    with pytest.raises(BootError, match=r"node 1 \(joint1\): configured 9 times.*it sent boot-up.*its supply"), \
            MotorDriver(cfg) as driver:
        driver.start()


def test_a_drive_whose_statusword_shows_no_state_is_not_booted(
        sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
    sim, cfg = sim_factory(make_config(1))
    simulator = sim.simulator_for(NODE)
    simulator.call(lambda: setattr(simulator.drive(NODE).faults, "garbled_statusword", True))
    with pytest.raises(BootError, match=r"node 1 \(joint1\): configured 9 times.*its statusword after NMT start,"
                                        r" 0x0201, is no CiA 402 state.*its firmware"), MotorDriver(cfg) as driver:
        driver.start()


def test_an_unexpected_error_in_a_reconfiguration_is_logged_counted_and_retried(
        driver_factory: Factory, caplog: pytest.LogCaptureFixture) -> None:
    sim, drive, record = one_drive(driver_factory)
    raised: list[str] = []

    def hook(point: str) -> None:
        if point == "boot: PDO mapping" and not raised:
            raised.append(point)
            raise RuntimeError("a fault of the driver's own, injected")

    with hooked(drive, hook) as boots:
        apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.05})
        wait_for(lambda: record.reconfigure_failures == 1, HANG_S, "the failed re-configuration counted")
        assert "RuntimeError: a fault of the driver's own, injected" in record.reconfigure_error
        wait_for(lambda: drive.boot.boot_count > boots and drive.cache.booted, HANG_S, "the retry")
    said = [r for r in caplog.records if "failed unexpectedly" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.ERROR and said[0].exc_info is not None
    assert record.reconfigure_failures == 1
    assert_enabled_as_asked(sim, drive)


def asked_of(drive: Drive) -> Objects:
    """The last value the driver's PDO configuration writes to each object (what it asks)."""
    return {(index, sub): int.from_bytes(data, "little") for index, sub, data, _ in mapping_writes(drive.plan)}


@pytest.mark.parametrize("eds", ["generic", pytest.param("maxon_epos2_70_10.eds", marks=requires_shared)])
def test_a_reset_whose_boot_up_is_lost_is_caught_by_what_the_drive_holds(
        eds: str, sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
    """No boot-up to hear: the generic drive's PDO objects read back (it has no 0x1020), the
    EPOS2's 0x1020 stamp, show the reset; configured again from an NMT reset, it is enabled only
    as asked."""
    sim, cfg = sim_factory(make_config(1, eds=eds if eds == "generic" else str(SHARED_EDS / eds),
                                       counts_per_rev=4096))
    apply_action(sim, {"action": "sdo_reset", "node": NODE, "index": 0x1017, "bootup": False})
    with MotorDriver(cfg) as driver:
        driver.start()
        drive = driver.drive("joint1")
        record = driver.supervisor.records["joint1"]
        drive.enable()
        assert sim_state(sim) is SimState.OPERATION_ENABLED
        held = pdo_objects(sim)
        assert {key: held[key] for key in asked_of(drive)} == asked_of(drive)
        assert record.boot_restarts == 1
        said = "0x1020 (verify configuration) holds" if eds != "generic" else "it does not hold its PDO configuration"
        assert said in record.boot_restart_why


def test_a_reset_heard_as_the_boot_reports_its_end_is_configured_again(driver_factory: Factory) -> None:
    """The drive resets after the boot's last look and its boot-up is heard before the boot's
    report reaches the supervisor (held there by a hook): not booted, configured again."""
    sim, drive, record = one_drive(driver_factory)
    fired: list[int] = []

    def hook(point: str) -> None:
        if point == "boot: started" and not fired:
            fired.append(drive.cache.bootups)
            apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.01})
            wait_for(lambda: drive.cache.bootups > fired[0], HANG_S, "its boot-up heard")

    with hooked(drive, hook) as boots:
        apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.05})
        wait_for(lambda: drive.boot.boot_count > boots + 1 and drive.cache.booted, HANG_S, "configured again")
    assert fired and record.boot_restarts == 1 and record.boot_restart_why == "it sent boot-up as its boot ended"
    assert_enabled_as_asked(sim, drive)


def test_a_reset_between_the_last_confirmation_and_the_start_whose_boot_up_is_lost_is_caught(
        driver_factory: Factory) -> None:
    """The drive resets, its boot-up lost, after its configuration was confirmed and before the NMT
    start (a hook at the start step): started, it would run on its default PDO mapping. The look
    after the start sees what it holds; configured again, it is enabled only as asked."""
    sim, drive, record = one_drive(driver_factory)
    simulator = sim.simulator_for(NODE)
    peer = simulator.drive(NODE)
    fired: list[bool] = []

    def hook(point: str) -> None:
        if point == "boot: start" and not fired:
            fired.append(True)
            simulator.call(lambda: peer._reset_node(peer._now, announce=False))  # no boot-up leaves it

    with hooked(drive, hook) as boots:
        apply_action(sim, {"action": "power_cycle", "node": NODE, "off_s": 0.05})
        wait_for(lambda: drive.boot.boot_count > boots and drive.cache.booted, HANG_S, "configured again")
    assert fired and record.boot_restarts == 1, record.boot_restart_why
    assert record.boot_restart_why.startswith("after NMT start: it does not hold its PDO configuration")
    assert_enabled_as_asked(sim, drive)


def test_the_0x1020_stamp_counts_days_from_1984_and_ms_from_midnight() -> None:
    assert configuration_stamp(441_763_200.0) == (0, 0)  # 1984-01-01 00:00:00 UTC
    assert configuration_stamp(441_763_200.0 + 86_400 * 3 + 3_723.5) == (3, 3_723_500)


def test_an_sdo_reset_at_write_0_is_refused_naming_the_range(
        sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
    sim, _ = sim_factory(make_config(1))
    with pytest.raises(ConfigError, match=r"sdo_reset at_writes \[3, 0\]: each count is 1 or more"):
        apply_action(sim, {"action": "sdo_reset", "node": NODE, "at_writes": [3, 0]})

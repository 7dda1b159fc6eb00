"""A second master on the bus is noticed, its drives are not commanded until it is gone, and
then they are configured again (not re-armed); a drive whose PDOs stop is reported stale."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from can_config import RoverConfig
from can_config.errors import DriveStateError
from motor_driver import MotorDriver, State
from motor_driver.diagnostics.health import ERROR, drive_health
from motor_driver.runtime.driver import FOREIGN_HOLD_S
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for
from .drive_states import stale

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]


class TruthWatch:
    """Every 5 ms: does the first driver's snapshot claim Operation Enabled while the simulated
    drive is not? Collects how long each such claim lasted."""

    def __init__(self, sim: SimService, driver: MotorDriver) -> None:
        self.sim, self.driver = sim, driver
        self.false_claims: list[float] = []
        self._since: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        runner = self.sim.simulators["can0"]
        drive = runner.drive(1)
        while not self._stop.is_set():
            claims = self.driver.drive("joint1").snapshot().verdict.usable
            truth = runner.call(lambda: drive.state.name) == "OPERATION_ENABLED"
            now = time.monotonic()
            if claims and not truth:
                self._since = self._since or now
            elif self._since is not None:
                self.false_claims.append(now - self._since)
                self._since = None
            time.sleep(0.005)

    def stop(self) -> list[float]:
        self._stop.set()
        self._thread.join()
        return self.false_claims


def judged_since(driver: MotorDriver, since: float, bus: str = "can0") -> None:
    """Wait until the supervisor has judged every drive in a period that began after ``since``
    (``time.monotonic()``): its host heartbeat of such a period is out, and a call handed to it
    after that is answered at the start of the next period, once that period's judgement is done
    (each period drains its calls, beats, then judges each drive). An absence of a mark after it
    is the supervisor's verdict, not a wait that happened to end first."""
    record = driver.supervisor.bus.bus_records[bus]
    wait_for(lambda: record.last_beat > since, 10.0, "a supervisor period after the traffic")
    driver.supervisor.call(lambda: None)


def test_a_second_driver_is_noticed_refused_and_control_comes_back(sim_factory: SimFactory) -> None:
    sim, cfg = sim_factory(make_config(1, watchdog_ms=10_000))
    first = MotorDriver(cfg).start()
    try:
        drive = first.drive("joint1")
        drive.enable()
        drive.set_velocity(30.0)
        wait_for(lambda: drive.snapshot().velocity_deg_s > 25.0, 2.0, "turning")
        boots = drive.boot.boot_count
        truth = TruthWatch(sim, first)
        t_second = time.monotonic()
        second = MotorDriver(cfg).start(take_over=True)  # a forgotten bench script forced: NMT reset, SDO, SYNC
        try:
            wait_for(lambda: bool(drive.watch.foreign_master), 1.0, "the first driver to notice the second")
            noticed = time.monotonic() - t_second
            assert "NMT command 0x81 to node 1" in drive.watch.foreign_master  # its reset came first
            wait_for(lambda: "SYNC frames this driver did not send" in drive.watch.foreign_master
                     and "this driver's own id: a second driver?" in drive.watch.foreign_master, 1.0, "its SYNC and heartbeat")
            with pytest.raises(DriveStateError, match="not under this driver's control: another master is on the bus"):
                drive.set_velocity(10.0)
            with pytest.raises(DriveStateError, match="another master"):
                drive.enable()
            health = drive_health(drive.snapshot(), heartbeat_period_s=0.1)
            assert health.level == ERROR and health.message.startswith("not under this driver's control")
            # the second was told to take the bus over: the first one's traffic is not held against it
            # (the second hears it: the first's own SYNC and heartbeat; its supervisor then judges)
            foreign, heard_from = second.buses["can0"].foreign, time.monotonic()
            wait_for(lambda: foreign.newest > heard_from, 10.0, "the second driver hearing the first's traffic")
            judged_since(second, foreign.newest)
            assert not second.drive("joint1").watch.foreign_master
        finally:
            second.close()
        # control back once it has been configured again (marking it for that and doing it are two
        # steps of the supervisor's: a wait on 'booted' alone could end between them)
        wait_for(lambda: not drive.watch.foreign_master and drive.cache.booted and drive.boot.boot_count > boots,
                 6.0, "control back, configured again")
        assert drive.boot.boot_count == boots + 1  # configured again, once ...
        wait_for(lambda: drive.snapshot().stamp > 0 and not stale(drive.snapshot()), 1.0, "fresh PDOs")
        assert drive.cache.state is not State.OPERATION_ENABLED and not drive.snapshot().verdict.usable  # ... not re-armed
        drive.enable()
        drive.move_to(drive.snapshot().angle_deg + 10.0, wait=True)
        false_claims = truth.stop()
        assert noticed < 1.0
        assert not [c for c in false_claims if c > 0.1], false_claims  # never claimed enabled while it was not
    finally:
        first.close()


def test_an_nmt_command_from_a_bench_tool_marks_the_drive(sim_factory: SimFactory) -> None:
    import can

    sim, cfg = sim_factory(make_config(2))
    with MotorDriver(cfg).start() as driver:
        bench = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:  # (the server takes the bench's frames as soon as its connect returns)
            bench.send(can.Message(arbitration_id=0x000, data=bytes([0x80, 2]), is_extended_id=False))  # pre-op node 2
            wait_for(lambda: bool(driver.drive("joint2").watch.foreign_master), 1.0, "node 2 marked")
            assert "NMT command 0x80 to node 2" in driver.drive("joint2").watch.foreign_master
            assert not driver.drive("joint1").watch.foreign_master  # only the node it was sent to
        finally:
            bench.shutdown()
        wait_for(lambda: not driver.drive("joint2").watch.foreign_master and driver.drive("joint2").cache.booted, 6.0,
                 "configured again after the quiet period")
        assert driver.drive("joint2").cache.nmt_state == "OPERATIONAL"


def test_stopped_pdos_are_reported_stale_within_n_sync_periods(sim_factory: SimFactory) -> None:
    sim, cfg = sim_factory(make_config(1, stale_after_syncs=5))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        drive.enable()
        wait_for(lambda: drive.snapshot().verdict.usable, 10.0, "fresh")
        apply_action(sim, {"action": "tpdos", "node": 1, "on": False})
        wait_for(lambda: stale(drive.snapshot()), 10.0, "stale")  # how soon: benchmarks (a test asserts no clock)
        state = drive.snapshot()
        assert not state.verdict.usable and state.data_age_s >= 0.05  # never before 5 SYNC periods of 10 ms
        health = drive_health(state, heartbeat_period_s=0.1)
        assert health.level == ERROR and health.message.startswith("no data for ")
        apply_action(sim, {"action": "tpdos", "node": 1, "on": True})
        wait_for(lambda: not stale(drive.snapshot()) and drive.snapshot().verdict.usable, 10.0, "fresh again")


def test_an_sdo_write_by_another_client_stops_and_marks_the_drive_but_a_read_does_not(sim_factory: SimFactory) -> None:
    import canopen

    from can_config import GENERIC_EDS, load_drive_od
    from virtual_can.server import RAWMODE_HOLD_S

    sim, cfg = sim_factory(make_config(1, watchdog_ms=10_000))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        drive.enable()
        drive.set_velocity(30.0)
        bench = canopen.Network()
        bench.connect(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:
            time.sleep(RAWMODE_HOLD_S + 0.02)
            node = bench.add_node(1, load_drive_od(GENERIC_EDS, 1))
            node.sdo.upload(0x1000, 0)  # a bench read (rovercan info, scan)
            # the driver's own read after it: its receive thread took the bench's request before
            # this answer (one bus, one order); then its supervisor judged
            assert drive.sdo_read(0x1000, 0)
            judged_since(driver, time.monotonic())
            assert not drive.watch.foreign_master and drive.snapshot().verdict.usable
            node.sdo.download(0x6065, 0, (1000).to_bytes(4, "little"))  # a write behind the driver's back
            wait_for(lambda: "SDO writes to node 1 from another client" in drive.watch.foreign_master, 1.0, "marked")
            runner = sim.simulators["can0"]
            wait_for(lambda: runner.call(lambda: runner.drive(1).state.name) != "OPERATION_ENABLED", 1.0,
                     "the quick stop the driver sent on losing control")
        finally:
            bench.disconnect()


def test_a_heartbeat_sent_before_the_drive_obeyed_nmt_start_is_no_foreign_master(sim_factory: SimFactory) -> None:
    """boot() ends with NMT start; a PRE-OPERATIONAL heartbeat the drive sent just before it
    obeyed can reach the receive thread after boot() returned (a loaded host, the socketcand
    server's queue). That is no state change behind the driver's back; leaving OPERATIONAL after
    the drive itself said OPERATIONAL is."""
    from can_config.objects import NmtState

    sim, cfg = sim_factory(make_config(1))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        runner = sim.simulators["can0"]
        wait_for(lambda: drive.cache.reported_nmt == "OPERATIONAL", 2.0, "the drive's own OPERATIONAL heartbeat")
        runner.call(lambda: setattr(runner.drive(1), "nmt", NmtState.PRE_OPERATIONAL))  # as after a reset
        wait_for(lambda: drive.cache.nmt_state == "PRE_OPERATIONAL", 1.0, "a PRE-OPERATIONAL heartbeat")
        # the supervisor marks that change (within its hold time); only then is the mark cleared,
        # or a late supervisor (a loaded machine) would mark it again after the clear
        wait_for(lambda: bool(drive.watch.foreign_master), 2.0, "the supervisor's mark of the change")
        record = driver.supervisor.records["joint1"]
        wait_for(lambda: record.behind_back[0] < time.monotonic() - FOREIGN_HOLD_S - 0.05, 2.0, "the hold over")
        def release() -> None:  # it went there on its own: the supervisor forgets its mark
            record.foreign_master, record.behind_back = "", (0.0, "")
        driver.supervisor.call(release)
        drive.boot.boot(reset=False)  # ... ends with NMT start
        drive.cache.on_heartbeat(0x701, bytearray([NmtState.PRE_OPERATIONAL]), 0.0)  # the one on its way
        judged_since(driver, time.monotonic())  # the supervisor has looked at it
        assert not drive.watch.foreign_master
        wait_for(lambda: drive.cache.nmt_state == "OPERATIONAL", 1.0, "the drive's own OPERATIONAL heartbeat")
        runner.call(lambda: setattr(runner.drive(1), "nmt", NmtState.PRE_OPERATIONAL))  # now it is a change
        wait_for(lambda: "went PRE_OPERATIONAL without an NMT command" in drive.watch.foreign_master, 1.0, "marked")


def sim_state(sim: SimService) -> tuple[str, float]:
    """The simulated drive's own CiA 402 state and shaft speed (rad/s): the truth, not the driver's view."""
    runner = sim.simulators["can0"]
    return runner.call(lambda: (runner.drive(1).state.name, runner.drive(1).omega))


def test_a_turning_drive_another_master_puts_in_pre_operational_is_stopped(sim_factory: SimFactory) -> None:
    """PRE-OPERATIONAL stops a drive's PDOs, not its motor: the quick stop the driver sends on
    losing control went as an RPDO only, which the drive ignored, and it kept turning at the
    commanded speed while the driver refused every command (seen: 30 deg/s for the 2 s until
    the driver took it back). It goes by SDO as well now."""
    import can

    sim, cfg = sim_factory(make_config(1, watchdog_ms=10_000))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        drive.enable()
        drive.set_velocity(30.0)
        wait_for(lambda: sim_state(sim)[1] > 0.4, 2.0, "turning")
        bench = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:
            bench.send(can.Message(arbitration_id=0x000, data=bytes([0x80, 1]), is_extended_id=False))
        finally:
            bench.shutdown()
        wait_for(lambda: bool(drive.watch.foreign_master), 1.0, "the other master noticed")
        wait_for(lambda: sim_state(sim) == ("SWITCH_ON_DISABLED", 0.0), 1.0, "the drive stopped by the driver's quick stop")


def test_a_drive_another_master_left_enabled_is_disabled_when_configured_again(sim_factory: SimFactory) -> None:
    """A bench tool enables a drive (SDO controlword writes) and goes quiet; the driver then
    configures the drive again without a reset and says it is not enabled: the drive must not
    be, or the next command from anyone moves a drive nobody armed."""
    import canopen

    from can_config import GENERIC_EDS, load_drive_od
    from virtual_can.server import RAWMODE_HOLD_S

    sim, cfg = sim_factory(make_config(1))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        bench = canopen.Network()
        bench.connect(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:
            time.sleep(RAWMODE_HOLD_S + 0.02)
            node = bench.add_node(1, load_drive_od(GENERIC_EDS, 1))
            for cw in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation
                node.sdo.download(0x6040, 0, cw.to_bytes(2, "little"))
            assert sim_state(sim)[0] == "OPERATION_ENABLED"
            wait_for(lambda: bool(drive.watch.foreign_master), 1.0, "the bench tool noticed")
        finally:
            bench.disconnect()
        wait_for(lambda: not drive.watch.foreign_master and drive.cache.booted, 6.0, "configured again after the quiet period")
        assert sim_state(sim)[0] == "SWITCH_ON_DISABLED"
        assert not drive.snapshot().verdict.usable
        drive.enable()  # armed again only when asked
        drive.move_to(10.0, wait=True)

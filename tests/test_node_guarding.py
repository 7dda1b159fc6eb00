"""Node guarding (CiA 301) for drives without a heartbeat consumer (0x1016), such as the
Technosoft iPOS and Ingenia Everest EDS files in ../shared/eds: the simulated drive's slave side
(toggle + state answers, life guarding with the 0x6007 reaction), the driver's choice of watch
per drive (``host_watch: auto | heartbeat | guarding``) and its refusal on a bus without remote
frames. The driver's guarding against a killed process runs in the kernel tier
(tests/test_kernel_tier.py), where remote frames exist."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import can
import canopen
import pytest

from can_config import GENERIC_EDS, load_drive_od, parse_config, with_bus_overrides
from can_config.errors import DriveTimeoutError, MotorError
from can_config.objects import OD, NmtCommand, NmtState
from motor_driver import MotorDriver, State
from motor_driver.protocol.safety import guard_settings
from virtual_can import SimService
from virtual_can.sim import DriveSimulator, SimulatedDrive
from virtual_can.sim.drive import State as SimState

from .conftest import REPO, SHARED_EDS, enable_letting_go, guarded_generic_eds, make_config, requires_shared, wait_for

TECHNOSOFT = SHARED_EDS / "technosoft_ipos_v1_04_via_ros2_canopen.eds"
GUARD = can.Message(arbitration_id=0x702, is_remote_frame=True, dlc=1, is_extended_id=False)


def guarded_drive() -> SimulatedDrive:
    drive = SimulatedDrive(2, load_drive_od(GENERIC_EDS, 2))
    drive.on_frame(can.Message(arbitration_id=0, data=bytes([NmtCommand.START, 2]), is_extended_id=False), 0.0)
    drive.store.values[(OD.GUARD_TIME, 0)] = 100
    drive.store.values[(OD.LIFE_TIME_FACTOR, 0)] = 3
    drive.store.values[(OD.ABORT_CONNECTION_OPTION, 0)] = 3  # quick stop
    return drive


def test_the_simulated_drive_answers_each_guard_with_a_toggling_state() -> None:
    drive = guarded_drive()
    answers = [drive.on_frame(GUARD, t * 0.1) for t in range(4)]
    assert [a[0].arbitration_id for a in answers] == [0x702] * 4
    assert [a[0].data[0] for a in answers] == [0x05, 0x85, 0x05, 0x85]  # OPERATIONAL, toggle 0, 1, 0, 1
    other = can.Message(arbitration_id=0x703, is_remote_frame=True, dlc=1, is_extended_id=False)
    assert drive.on_frame(other, 0.5) == []  # another node's guard


def test_life_guarding_stops_the_drive_after_guard_time_x_factor() -> None:
    drive = guarded_drive()
    drive.state = SimState.OPERATION_ENABLED
    drive.on_frame(GUARD, 1.0)
    out = []
    now = 1.0
    while now < 1.25:  # within 100 ms x 3: nothing
        now += 0.01
        out += drive.tick(now, 0.01)
    assert drive.state == SimState.OPERATION_ENABLED
    while now < 1.4:
        now += 0.01
        out += drive.tick(now, 0.01)
    emcys = [m for m in out if m.arbitration_id == 0x082]
    assert emcys and int.from_bytes(emcys[0].data[:2], "little") == 0x8130
    assert drive.state in (SimState.QUICK_STOP_ACTIVE, SimState.SWITCH_ON_DISABLED)


@pytest.mark.parametrize(("behaviour", "after"), [(None, NmtState.OPERATIONAL), (0, NmtState.PRE_OPERATIONAL),
                                                  (1, NmtState.OPERATIONAL), (2, NmtState.STOPPED)])
@pytest.mark.parametrize("watch", ["heartbeat", "guarding"])
def test_a_lost_master_takes_the_drive_where_its_0x1029_says(watch: str, behaviour: int | None,
                                                             after: NmtState) -> None:
    """CiA 301 0x1029:1 on a communication error (a heartbeat consumer's timeout, a life guarding
    event): 0 PRE-OPERATIONAL (its PDOs stop: the default of most drives that list it, the
    Faulhaber's, ros2_canopen's), 1 no change, 2 STOPPED; a drive without it stays as it was. The
    0x6007 reaction and its EMCY come all the same."""
    drive = guarded_drive()
    if behaviour is not None:
        drive.store.values[(OD.ERROR_BEHAVIOUR, 1)] = behaviour
    drive.state = SimState.OPERATION_ENABLED
    if watch == "heartbeat":
        drive.store.values[(OD.GUARD_TIME, 0)] = 0
        drive.store.values[(OD.CONSUMER_HEARTBEAT_TIME, 1)] = 127 << 16 | 100
        drive._load_consumers()
        drive.on_frame(can.Message(arbitration_id=0x77F, data=bytes([5]), is_extended_id=False), 1.0)
    else:
        drive.on_frame(GUARD, 1.0)
    out = [m for t in range(1, 50) for m in drive.tick(1.0 + t * 0.01, 0.01)]
    emcys = [m for m in out if m.arbitration_id == 0x082]
    assert emcys and int.from_bytes(emcys[0].data[:2], "little") == 0x8130
    assert drive.state in (SimState.QUICK_STOP_ACTIVE, SimState.SWITCH_ON_DISABLED)
    assert drive.nmt == after


def test_life_guarding_waits_for_the_first_guard() -> None:
    drive = guarded_drive()
    drive.state = SimState.OPERATION_ENABLED
    out = [m for t in range(1, 100) for m in drive.tick(t * 0.01, 0.01)]
    assert not [m for m in out if m.arbitration_id == 0x082] and drive.state == SimState.OPERATION_ENABLED
    assert drive._guarded_at is None
    assert NmtState(drive.nmt) == NmtState.OPERATIONAL


def test_guard_settings_cover_the_host_timeout() -> None:
    cfg = make_config(1, heartbeat_period_ms=100, host_timeout_ms=350).drives[0]
    guard_ms, factor = guard_settings(cfg)
    assert guard_ms == 100 and guard_ms * factor >= 350 and factor == 4


@requires_shared
def test_a_guarded_drive_on_socketcand_is_not_armed_and_says_why() -> None:
    """socketcand's rawmode has no remote frames: a drive that can only be guarded (Technosoft:
    0x100C/0x100D, no 0x1016) gets no host watch there, named, and is not enabled."""
    config = make_config(1, eds=str(TECHNOSOFT), counts_per_rev=4096)
    with SimService.from_config(config, port=0) as sim:
        cfg = with_bus_overrides(config, host="127.0.0.1", port=sim.port)
        with MotorDriver(cfg) as driver:
            driver.start()
            drive = driver.drive("joint1")
            assert drive.watch.watch_mode() == "guarding"
            assert drive.watch.host_watch is None
            assert "remote frames" in (drive.watch.host_watch_problem or "")
            with pytest.raises(MotorError, match="remote frames"):
                drive.enable()


@requires_shared
def test_the_bench_arms_a_guarded_drive_on_socketcand_only_when_told() -> None:
    """`rovercan enable` of a drive that can only be guarded, on socketcand: refused, naming the
    missing host watch; with --allow-no-host-watch it arms, with the warning on stderr."""
    config = make_config(1, eds=str(TECHNOSOFT), counts_per_rev=4096)
    with SimService.from_config(config, port=0) as sim:
        bus = ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={sim.port}"]
        drive = ["--eds", str(TECHNOSOFT), "--counts-per-rev", "4096"]
        refused = subprocess.run([sys.executable, "-m", "rovercan", "enable", "1", *drive, *bus], cwd=REPO,
                                 capture_output=True, text=True, timeout=120)
        assert refused.returncode == 2, refused.stderr  # refused before anything was sent
        assert "remote frames" in refused.stderr and "--allow-no-host-watch" in refused.stderr
        assert "safety check failed: drive heartbeat" not in refused.stderr  # it keeps its heartbeat here
        allowed = subprocess.run([sys.executable, "-m", "rovercan", "enable", "1", "--allow-no-host-watch", *drive,
                                  *bus], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert allowed.returncode == 0, allowed.stderr
        assert "NOTHING stops it" in allowed.stderr


def test_enable_waits_until_a_guarded_drive_answers_guards(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A node-guarded drive's life guarding starts at the first guard it hears (CiA 301): enabled
    before that, nothing stops it if the host dies. The guard answers are counted by the receive
    thread: boot's own NMT start had counted as one (a review found the guarded path always
    passed). On a python-can virtual bus (it carries remote frames, as a kernel bus does), the
    supervisor's guards held back across a new boot: enable is refused, nothing sent; let go,
    it returns with the drive guarded."""
    eds = guarded_generic_eds(tmp_path / "guarded.eds")
    channel = f"guarding-{tmp_path.name}"
    config = parse_config({"buses": [{"name": "can0", "interface": "virtual", "channel": channel}],
                           "drives": [{"name": "joint1", "node_id": 1, "eds": str(eds), "host_watch": "guarding",
                                       "heartbeat_timeout_ms": 30_000}]},  # held guards: not lost meanwhile
                          source=tmp_path / "rover.yaml")
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    with can.Bus(interface="virtual", channel=channel) as sim_bus, DriveSimulator(sim_bus, [sim_drive]) as runner, \
            MotorDriver(config) as driver:
        runner.start()
        driver.start()
        drive = driver.drive("joint1")
        assert drive.cache.guarding, drive.watch.host_watch
        # guards answered before the new boot: its count starts from theirs, not from zero
        wait_for(lambda: drive.cache.guard_answers >= 3, 30.0, "three guard answers")
        held = threading.Event()
        held.set()
        send_guard = drive.watch.send_guard
        monkeypatch.setattr(drive.watch, "send_guard", lambda: None if held.is_set() else send_guard())
        drive.boot.boot()  # told to be guarded again: its life guarding waits for a first guard
        with pytest.raises(DriveTimeoutError, match=r"enable refused: the drive is not watching the host after .* s: 0"
                                                    r" of the 2 guard answers it needs"):
            drive.enable()
        assert runner.call(lambda: sim_drive.state) != SimState.OPERATION_ENABLED
        enable_letting_go(drive, held)
        assert runner.call(lambda: sim_drive._guarded_at) is not None and drive.cache.state is State.OPERATION_ENABLED


def guarded_config(tmp_path: Path, channel: str, **drive: object) -> tuple[Path, object]:
    eds = guarded_generic_eds(tmp_path / "guarded.eds")
    return eds, parse_config({"buses": [{"name": "can0", "interface": "virtual", "channel": channel}],
                              "drives": [{"name": "joint1", "node_id": 1, "eds": str(eds), "host_watch": "guarding",
                                          **drive}]}, source=tmp_path / "rover.yaml")


@pytest.mark.parametrize("index", [OD.GUARD_TIME, OD.LIFE_TIME_FACTOR])
def test_a_config_sdo_entry_cannot_turn_a_guarded_drives_watch_off(tmp_path: Path, index: int) -> None:
    """0x100D = 0 in the config's ``sdo:`` list was written after the host watch and turned it off
    (life guarding stops at a factor of 0), the drive then armed and left moving when the host
    fell silent (an independent review's finding). 0x100C and 0x100D are the driver's, as 0x1016 is:
    the boot refuses the entry, naming it and what to set instead."""
    channel = f"guard-sdo-{index:X}-{tmp_path.name}"
    eds, config = guarded_config(tmp_path, channel, sdo=[{"index": index, "value": 0}])
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    with can.Bus(interface="virtual", channel=channel) as sim_bus, DriveSimulator(sim_bus, [sim_drive]) as runner, \
            MotorDriver(config) as driver:  # type: ignore[arg-type]
        runner.start()
        with pytest.raises(MotorError, match=rf"0x{index:04X}.*guarded drive watches the host.*heartbeat_period_ms"):
            driver.start()
        assert runner.call(lambda: sim_drive.state) != SimState.OPERATION_ENABLED


@pytest.mark.parametrize("allowed", [False, True])
def test_a_guard_setting_the_drive_did_not_keep_refuses_enable(tmp_path: Path, allowed: bool) -> None:
    """A drive that keeps another life time factor than the one written (0: guarding off) was
    said FAIL by the boot's safety check and armed all the same. The watch read back wrong counts
    as no watch: enable is refused naming what was read, nothing sent; allow_no_host_watch
    overrides, as it does for a drive without one."""
    channel = f"guard-kept-{allowed}-{tmp_path.name}"
    eds, config = guarded_config(tmp_path, channel, allow_no_host_watch=allowed)
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    write = sim_drive.store.write

    def keeps_zero(index: int, subindex: int, raw: bytes) -> None:
        write(index, subindex, bytes(len(raw)) if index == OD.LIFE_TIME_FACTOR else raw)

    sim_drive.store.write = keeps_zero  # type: ignore[method-assign]
    with can.Bus(interface="virtual", channel=channel) as sim_bus, DriveSimulator(sim_bus, [sim_drive]) as runner, \
            MotorDriver(config) as driver:  # type: ignore[arg-type]
        runner.start()
        driver.start()
        drive = driver.drive("joint1")
        assert [c.check for c in drive.boot.safety if c.status not in ("pass", "n/a")] == ["host watch (node guarding)"]
        if allowed:  # armed, and said to be armed without a watch, naming what was read
            assert drive.watch.host_watch is None and "read back wrong" in str(drive.watch.host_watch_problem)
            drive.enable()
            assert drive.cache.state is State.OPERATION_ENABLED
            return
        with pytest.raises(MotorError, match=r"enable refused: its host watch read back wrong after boot"
                                             r" \(0x100C/0x100D is 100 ms x 0"):
            drive.enable()
        assert runner.call(lambda: sim_drive.state) != SimState.OPERATION_ENABLED


def test_safety_check_judges_a_guarded_drive_by_its_guard_settings(tmp_path: Path) -> None:
    """``rovercan safety-check`` judged every drive by 0x1016: a correctly guarded drive failed
    "host watch: no 0x1016" and "drive heartbeat: expected 100 ms, got 0" (a review's finding),
    and a guard turned off would have gone unseen among those. Read from the bus by a network of
    its own, beside the driver that booted the drive, as the command reads it."""
    from rovercan.bench.checks import _drive_safety_rows

    channel = f"guard-check-{tmp_path.name}"
    eds, config = guarded_config(tmp_path, channel)
    sim_drive = SimulatedDrive(1, load_drive_od(eds, 1))
    with can.Bus(interface="virtual", channel=channel) as sim_bus, DriveSimulator(sim_bus, [sim_drive]) as runner, \
            MotorDriver(config) as driver, can.Bus(interface="virtual", channel=channel) as tool_bus:  # type: ignore[arg-type]
        runner.start()
        driver.start()
        network = canopen.Network(tool_bus)
        network.connect()
        try:
            rows = {r["check"]: r for r in _drive_safety_rows(network, config.drives[0], config.buses[0])}  # type: ignore[attr-defined]
        finally:
            network.disconnect()
    guard_ms, factor = guard_settings(config.drives[0])  # type: ignore[attr-defined]
    assert rows["host watch (node guarding)"]["status"] == "pass", rows
    assert rows["host watch (node guarding)"]["actual"] == f"{guard_ms} ms x {factor}"
    assert "host watch" not in rows and all(r["status"] in ("pass", "n/a") for r in rows.values()), rows

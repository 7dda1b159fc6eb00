"""Look before you reset: a bench command (and the driver at start) listens for another master
before its first NMT command or enable, and refuses beside a live one unless told --force. The
other master here is the rover's driver in a process of its own; an independent listener shows
that its drive never left Operation Enabled."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

import can
import pytest

from can_config import load_drive_od
from can_config.config import GENERIC_EDS
from motor_driver import ForeignMasterError, MotorDriver
from motor_driver.protocol.pdo import plan_pdos
from virtual_can import SimDriveSpec, SimService

from .conftest import REPO, make_config, rovercan_cli
from .test_host_loss import CLIENT, statusword_enabled, watches_heard_all, watching, write_config


def statusword_tpdos(eds: Path, node: int) -> dict[int, int]:
    """COB-ID -> byte offset of every TPDO carrying the statusword, as the driver maps them (the
    one sent at each SYNC shows the state all the time, not only on a change)."""
    out = {}
    for pdo in plan_pdos(load_drive_od(eds, node), node).tpdos:
        offset = 0
        for index, _, dtype in pdo.objects:
            if index == 0x6041:
                out[pdo.cob_id] = offset
            offset += {0x2: 1, 0x5: 1, 0x3: 2, 0x6: 2}.get(dtype, 4)
    return out


def rovercan(*args: str) -> subprocess.CompletedProcess[str]:
    return rovercan_cli(*args)


def bench(sim: SimService) -> list[str]:
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={sim.port}"]


def test_bench_commands_beside_a_running_driver_refuse_and_its_drive_stays_enabled(tmp_path: Path) -> None:
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "wheel", 4096)], port=0) as sim:
        config = write_config(tmp_path / "rover.yaml", sim.port, [("wheel", 1, "can0", GENERIC_EDS)])
        proc = subprocess.Popen([sys.executable, str(CLIENT), str(config), "30"], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "READY"
            sync_tpdos = statusword_tpdos(GENERIC_EDS, 1)
            with watching(sim, ["can0"]) as watches:
                clients = len(sim.server.clients)  # the driver's and the watch's
                for args in (["jog", "1", "10", "--for", "0.5", "--counts-per-rev", "4096"],
                             ["move", "1", "45", "--counts-per-rev", "4096"], ["nmt", "reset", "1"],
                             ["enable", "1"]):
                    result = rovercan(*args, *bench(sim))
                    assert result.returncode == 1, (args, result.stderr)
                    assert "another master is live on the bus" in result.stderr and "--force" in result.stderr, result.stderr
                    assert "SYNC frames" in result.stderr or "heartbeats of node 127" in result.stderr, result.stderr
                watches_heard_all(sim, watches, clients)  # the bench commands' connections gone
            words = [int.from_bytes(m.data[sync_tpdos[m.arbitration_id]:][:2], "little")
                     for _, m in watches["can0"].frames if m.arbitration_id in sync_tpdos]
            assert words and all(statusword_enabled(w) for w in words), [hex(w) for w in words]
            sdo_or_nmt = [m for _, m in watches["can0"].frames if m.arbitration_id in (0x000, 0x601)]
            assert not sdo_or_nmt, sdo_or_nmt  # the bench commands sent nothing at all
            assert proc.poll() is None  # the rover's driver runs on, untroubled
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=10)


class PassiveMaster:
    """Another master that only proves it is alive: the host heartbeat and SYNC."""

    def __init__(self, sim: SimService) -> None:
        self.bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.wait(0.02):
            self.bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
            self.bus.send(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False))

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()


def test_with_force_the_bench_commands_run_beside_a_live_master() -> None:
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "wheel", 4096)], port=0) as sim:
        master = PassiveMaster(sim)
        try:
            refused = rovercan("jog", "1", "20", "--for", "0.5", *bench(sim))
            assert refused.returncode == 1 and "another master" in refused.stderr
            for args in (["jog", "1", "20", "--for", "0.5"], ["move", "1", "30"], ["nmt", "reset", "1"]):
                result = rovercan(*args, "--force", *bench(sim))
                assert result.returncode == 0, (args, result.stderr)
        finally:
            master.close()


def test_the_driver_refuses_to_start_beside_a_live_master_unless_told_to_take_over() -> None:
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "joint1", 4096)], port=0) as sim:
        from can_config import with_bus_overrides
        cfg = with_bus_overrides(make_config(1), host=sim.host, port=sim.port)
        master = PassiveMaster(sim)
        try:
            driver = MotorDriver(cfg)
            with pytest.raises(ForeignMasterError, match="another master is live") as err:
                driver.start()
            assert "SYNC frames this driver did not send" in err.value.evidence
            drive = sim.simulator_for(1).drive(1)
            assert sim.simulator_for(1).call(lambda: drive.counters["sdo"]) == 0  # nothing was sent to it
            with MotorDriver(cfg) as forced:
                forced.start(take_over=True)
                forced.drive("joint1").enable()
        finally:
            master.close()


def test_the_bench_listens_longer_than_any_period_a_config_allows() -> None:
    """A master whose host heartbeat and SYNC come every 1000 ms (the most a config allows) is
    heard at least once in the bench's default window; the schema's bounds are read, not copied."""
    from can_config.fields import BUS_FIELDS
    from motor_driver.bus.traffic import LOOK_BENCH_S

    longest_s = max(BUS_FIELDS[key].high for key in ("host_heartbeat_ms", "sync_period_ms")) / 1000  # type: ignore[operator]
    assert longest_s < LOOK_BENCH_S


def test_a_master_with_a_one_second_period_is_heard_and_the_wait_said_on_screen() -> None:
    """Another master sending its heartbeat and SYNC once a second (the attack that reset its
    drive in 4 of 8 runs when the bench listened 0.2 s): `move` refuses, says how long it
    listened, and nothing of it reaches the bus (no NMT, no RPDO)."""
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "wheel", 4096)], port=0) as sim, \
            can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) as master:
        stop = threading.Event()

        def beat() -> None:
            while not stop.is_set():  # a paced stream: the other master's 1 s period
                master.send(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False))
                master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
                stop.wait(1.0)

        thread = threading.Thread(target=beat, daemon=True)
        thread.start()
        try:
            with watching(sim, ["can0"]) as watches:
                moved = rovercan("move", "1", "45", "--counts-per-rev", "4096", *bench(sim))
        finally:
            stop.set()
            thread.join(10.0)
    assert moved.returncode == 1 and "another master is live on the bus" in moved.stderr, moved.stderr
    assert "listening 1.1 s for another master" in moved.stderr
    sent = [m for w in watches.values() for _, m in w.frames if m.arbitration_id in (0x000, 0x201, 0x301, 0x401, 0x601)]
    assert not sent, sent

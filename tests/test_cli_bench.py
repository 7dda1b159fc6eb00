"""The bench CLI as real subprocesses against `rovercan sim` in another process, error paths included."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import REPO, SHARED_TRAFFIC, requires_shared, rovercan_cli, rovercan_sim
from .test_sim_cli import free_port

GENERIC = str(REPO / "can_config" / "data" / "generic_cia402.eds")


@pytest.fixture(scope="module")
def sim_port() -> Iterator[int]:
    with rovercan_sim("--drives", "2") as port:
        yield port


def run(port: int | None, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    bus = ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={port}"] if port else []
    return rovercan_cli(*args, *bus, timeout=timeout)


def as_json(result: subprocess.CompletedProcess[str]) -> object:
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_scan_finds_both_drives(sim_port: int) -> None:
    rows = as_json(run(sim_port, "scan", "--json", "--listen", "0.5"))
    assert [r["node"] for r in rows] == [1, 2]  # type: ignore[union-attr, index]
    assert rows[0]["vendor"] == "0x00524F56" and rows[0]["device_type"] == "0x00020192"  # type: ignore[index]


def test_info_decodes_identity_firmware_and_pdos(sim_port: int) -> None:
    info = as_json(run(sim_port, "info", "2", "--eds", GENERIC, "--json"))
    assert info["device_name"] == "rovercan generic CiA 402 servo"  # type: ignore[index]
    assert info["firmware"] == "1.0.0"  # type: ignore[index]
    assert "PROFILE_POSITION" in info["supported_modes"]  # type: ignore[index]
    assert info["tpdos"][0] == "1: 0x182 type 255: 0x6041 Statusword"  # type: ignore[index]
    assert info["error_history"] == []  # type: ignore[index]


def test_sdo_read_write_and_errors(sim_port: int) -> None:
    assert as_json(run(sim_port, "sdo", "write", "1", "0x6065", "250", "--eds", GENERIC, "--json"))["written"] == "fa 00 00 00"  # type: ignore[index]
    assert as_json(run(sim_port, "sdo", "read", "1", "6065", "--eds", GENERIC, "--json"))["value"] == 250  # type: ignore[index]
    abort = run(sim_port, "sdo", "read", "1", "0x2345")
    assert abort.returncode == 1 and "0x06020000 object does not exist" in abort.stderr
    for guarded in ("0x607A", "0x607D:2", "0x6040", "0x1600:1", "0x1017"):  # limits cannot be bypassed from the CLI
        refused = run(sim_port, "sdo", "write", "1", guarded, "1", "--eds", GENERIC)
        assert refused.returncode == 2 and "is refused" in refused.stderr  # refused before anything was sent
    ro = run(sim_port, "sdo", "write", "1", "0x1000", "5", "--eds", GENERIC)
    assert ro.returncode == 1 and "attempt to write a read only object" in ro.stderr
    bad = run(sim_port, "sdo", "read", "1", "nope")
    assert bad.returncode == 2 and "expected INDEX[:SUB]" in bad.stderr
    timeout = run(sim_port, "sdo", "read", "42", "0x1000")
    assert timeout.returncode == 1 and "node 42: no answer" in timeout.stderr and "termination" in timeout.stderr
    no_bus = run(None, "sdo", "read", "1", "0x1000")
    assert no_bus.returncode == 2 and "no bus given" in no_bus.stderr


def test_sdo_read_knows_the_standard_objects_without_an_eds(sim_port: int) -> None:
    status = as_json(run(sim_port, "sdo", "read", "1", "0x6041", "--json"))
    assert status["name"] == "Statusword" and isinstance(status["value"], int)  # type: ignore[index]
    assert status["meaning"].startswith("SWITCH_ON_DISABLED: ")  # type: ignore[index]
    assert "SWITCH_ON_DISABLED" in status["meaning"].split(": ")[1]  # type: ignore[index]
    mode = as_json(run(sim_port, "sdo", "read", "1", "0x6061", "--json"))
    assert mode["meaning"] in ("NO_MODE", "PROFILE_POSITION") and mode["name"]  # type: ignore[index]
    device = as_json(run(sim_port, "sdo", "read", "1", "0x1000", "--json"))
    assert device["value"] == 0x00020192 and device["name"]  # type: ignore[index]


def test_nmt_and_drive_commands(sim_port: int) -> None:
    assert run(sim_port, "nmt", "preop", "all").returncode == 0
    moved = as_json(run(sim_port, "move", "2", "30", "--counts-per-rev", "4096", "--speed", "120", "--json"))
    assert moved["angle_deg"] == pytest.approx(30.0, abs=0.2)  # type: ignore[index]
    # the state it left the drive in, read after the disable (it said OPERATION_ENABLED)
    assert moved["state"] in ("READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED", "SWITCHED_ON"), moved  # type: ignore[index]
    assert moved["verdict"].startswith("not armed"), moved  # type: ignore[index]
    jog = as_json(run(sim_port, "jog", "2", "45", "--for", "0.8", "--counts-per-rev", "4096", "--json"))
    assert jog["velocity_deg_s"] == pytest.approx(45.0, abs=2.0)  # type: ignore[index]
    enabled = as_json(run(sim_port, "enable", "1", "--counts-per-rev", "4096", "--json"))
    assert enabled["state"] == "OPERATION_ENABLED"  # type: ignore[index]
    homed = as_json(run(sim_port, "home", "2", "--counts-per-rev", "4096", "--json"))
    assert homed["angle_deg"] == pytest.approx(0.0, abs=0.05)  # type: ignore[index]
    assert as_json(run(sim_port, "fault-reset", "2", "--counts-per-rev", "4096", "--json"))["state"]  # type: ignore[index]
    disabled = as_json(run(sim_port, "disable", "2", "--counts-per-rev", "4096", "--json"))
    assert disabled["state"] in ("READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED")  # type: ignore[index]
    missing = run(sim_port, "move", "9", "10")
    assert missing.returncode == 1 and "no boot-up message" in missing.stderr
    nan = run(sim_port, "move", "1", "nan", "--counts-per-rev", "4096")
    assert nan.returncode == 2 and "not a finite number" in nan.stderr  # refused as input, before the bus


def test_monitor_record_replay_decode(sim_port: int, tmp_path: Path) -> None:
    log = tmp_path / "bus.log"
    rec = subprocess.Popen([sys.executable, "-m", "rovercan", "record", str(log), "--seconds", "6", "-i", "socketcand",
                            "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={sim_port}"], cwd=REPO,
                           stderr=subprocess.PIPE, text=True)
    mon = subprocess.Popen([sys.executable, "-m", "rovercan", "monitor", "--seconds", "6", "--node", "1", "--eds",
                            GENERIC, "-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1",
                            f"port={sim_port}"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert rec.stderr is not None and mon.stderr is not None
    assert "recording" in rec.stderr.readline() and "listening" in mon.stderr.readline()
    assert run(sim_port, "move", "1", "20", "--counts-per-rev", "4096").returncode == 0
    out, _ = mon.communicate(timeout=30)
    rec.wait(timeout=30)
    assert "NMT RESET_NODE node 1" in out and "BOOT-UP node 1" in out and "SDO write 0x1A00:1" in out
    assert "TPDO2 node 1: position_actual_value=" in out  # decoded by the driver's mapping
    decoded = as_json_lines(run(None, "decode", str(log), "--json"))
    texts = [d["text"] for d in decoded]
    assert any(t.startswith("RPDO2 node 1") for t in texts) and "SYNC" in texts
    assert run(sim_port, "replay", str(log), "--fast").returncode == 0


def monitor(port: int) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "rovercan", "monitor", "-i", "socketcand", "-c", "can0",
                             "--bus-kwargs", "host=127.0.0.1", f"port={port}"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_monitor_into_a_pipe_that_closes_ends_quietly(sim_port: int) -> None:
    """'rovercan monitor | head' on the bench: the reader goes away, the monitor ends with 0 and
    no broken-pipe message."""
    mon = monitor(sim_port)
    try:
        assert mon.stdout is not None and mon.stderr is not None
        assert "listening" in mon.stderr.readline()
        assert run(sim_port, "sdo", "read", "1", "0x1000").returncode == 0
        assert mon.stdout.readline()
        mon.stdout.close()
        assert run(sim_port, "sdo", "read", "1", "0x1000").returncode == 0  # more lines: the write fails
        assert mon.wait(timeout=10) == 0
        assert "Broken pipe" not in mon.stderr.read()
    finally:
        mon.kill()


def test_monitor_says_when_the_bus_server_goes_away() -> None:
    """python-can's socketcand client reads a closed connection as 'no frame' forever; the monitor
    notices, says so and exits 1 instead of spinning on a dead socket."""
    port = free_port()
    sim = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--drives", "1", "--port", str(port)],
                           cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    mon: subprocess.Popen[str] | None = None
    try:
        assert sim.stdout is not None and "simulated drive" in sim.stdout.readline()
        mon = monitor(port)
        assert mon.stderr is not None and "listening" in mon.stderr.readline()
        sim.send_signal(signal.SIGTERM)
        sim.wait(timeout=30)
        assert mon.wait(timeout=10) == 1
        assert "closed the connection" in mon.stderr.read()
    finally:
        sim.kill()
        if mon is not None:
            mon.kill()


def as_json_lines(result: subprocess.CompletedProcess[str]) -> list[dict[str, object]]:
    assert result.returncode == 0, result.stderr
    return [json.loads(line) for line in result.stdout.splitlines()]


@requires_shared
def test_decode_the_real_pcan_trace() -> None:
    result = run(None, "decode", str(SHARED_TRAFFIC / "hilch_pcan2_canopen301.trc"))
    assert result.returncode == 0, result.stderr
    assert "heartbeat node 15: OPERATIONAL" in result.stdout
    assert "SDO" in result.stdout and "TPDO1 node 15" in result.stdout


def test_step_test_png_and_metrics(sim_port: int, tmp_path: Path) -> None:
    out = tmp_path / "step"
    metrics = as_json(run(sim_port, "step-test", "1", "--step", "90", "--seconds", "2.5", "--counts-per-rev", "4096",
                          "--out", str(out), "--json"))
    assert (tmp_path / "step.png").stat().st_size > 10_000
    # profile: 90 deg/s, 360 deg/s^2 (the config defaults): accelerating 0.25 s, cruising,
    # 90 deg take 0.25 + 0.75 + 0.25 = 1.25 s; 10 %->90 % of the way is about 0.8 s
    assert metrics["rise_time_s"] == pytest.approx(0.8, abs=0.15)  # type: ignore[index]
    assert metrics["overshoot_pct"] < 1.0  # type: ignore[index]
    assert metrics["settling_time_s"] == pytest.approx(1.2, abs=0.2)  # type: ignore[index]
    assert metrics["steady_state_error_deg"] < 0.2  # type: ignore[index]
    # the simulator's default wheel model: 0.03 Nm of friction plus 1e-4 kg m^2 x 6.3 rad/s^2
    assert 0.025 < metrics["peak_torque_nm"] < 0.1  # type: ignore[index]


def test_plan_and_can_up(tmp_path: Path) -> None:
    rows = as_json(run(None, "plan", "--config", str(REPO / "config" / "rover.yaml"), "--json"))
    totals = [r for r in rows if r["what"] == "TOTAL"]  # type: ignore[union-attr, index]
    assert len(totals) == 2 and all(0 < t["load_pct"] < 50 for t in totals)  # type: ignore[index]  # a number
    heavy = tmp_path / "heavy.yaml"
    heavy.write_text("buses: [{name: can0, interface: socketcand, channel: can0, bitrate: 125000, sync_period_ms: 1}]\n"
                     "drives: [{name: a, node_id: 1}, {name: b, node_id: 2}]\n")
    over = run(None, "plan", "--config", str(heavy))
    assert over.returncode == 1 and "cannot carry" in over.stderr
    dry = run(None, "can-up", "can0", "--bitrate", "1000000", "--dry-run")
    assert dry.returncode == 0
    assert "ip link set can0 type can bitrate 1000000 restart-ms 100 berr-reporting on" in dry.stdout
    assert "ip link set can0 txqueuelen 1000" in dry.stdout
    evil = run(None, "can-up", "can0;reboot", "--bitrate", "1000000", "--dry-run")
    assert evil.returncode == 2 and "expected a Linux interface name" in evil.stderr
    slow = run(None, "can-up", "can0", "--bitrate", "2000000", "--dry-run")
    assert slow.returncode == 2 and "out of range 10000..1000000" in slow.stderr
    vcan = run(None, "can-up", "vcan0", "--dry-run")  # CI's virtual interface: created, no bitrate
    assert vcan.returncode == 0 and "ip link add dev vcan0 type vcan" in vcan.stdout and "bitrate" not in vcan.stdout
    from_config = run(None, "can-up", "can1", "--dry-run", "--config", str(REPO / "config" / "rover.yaml"))
    assert from_config.returncode == 0, from_config.stderr
    assert "bitrate 1000000 bit/s, restart-ms 100, txqueuelen 1000 from bus can1 of" in from_config.stdout
    tuned = tmp_path / "tuned.yaml"  # the bring-up's settings from the config, a flag over one of them
    tuned.write_text("buses: [{name: can0, interface: socketcan, channel: can0, bitrate: 500000, restart_ms: 250,"
                     " txqueuelen: 64}]\ndrives: [{name: a, node_id: 1}]\n")
    from_tuned = run(None, "can-up", "can0", "--dry-run", "--config", str(tuned), "--restart-ms", "0")
    assert from_tuned.returncode == 0, from_tuned.stderr
    assert "ip link set can0 type can bitrate 500000 restart-ms 0 berr-reporting on" in from_tuned.stdout
    assert "ip link set can0 txqueuelen 64" in from_tuned.stdout
    assert "from --restart-ms; the rest from bus can0 of" in from_tuned.stdout
    bare = run(None, "can-up", "can0", "--dry-run")  # the embedded default knows the bitrate
    assert bare.returncode == 0 and "type can bitrate 1000000" in bare.stdout

"""`rovercan sim` as a real subprocess; python-can's socketcand client and canopen's
RemoteNode in this (another) process see heartbeats and PDOs and read 0x1018 / 0x6041."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import canopen
import pytest

from can_config import GENERIC_EDS
from can_config.realtime import DRIVER_PRIORITY

from .conftest import REPO, drain, realtime_allowed, requires_ros, stop_process, wait_for


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rovercan(*args: str) -> list[str]:
    return [sys.executable, "-m", "rovercan", *args]


@pytest.fixture
def sim_process() -> Iterator[tuple[subprocess.Popen[str], int]]:
    port = free_port()
    proc = subprocess.Popen(rovercan("sim", "--drives", "2", "--port", str(port)), cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    assert "2 simulated drive(s)" in first, first + (proc.stderr.read() if proc.poll() is not None else "")
    yield proc, port
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_sim_prints_python_can_arguments_and_stops_on_sigterm(sim_process: tuple[subprocess.Popen[str], int]) -> None:
    proc, port = sim_process
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert f"-i socketcand -c can0 --bus-kwargs host=127.0.0.1 port={port}" in line
    proc.send_signal(signal.SIGTERM)
    try:
        code = proc.wait(timeout=30)  # generous: the whole suite loads two cores
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"rovercan sim did not stop on SIGTERM; stderr: {err[-3000:]}") from None
    assert code == 0


def test_other_process_sees_heartbeats_pdos_and_reads_identity(sim_process: tuple[subprocess.Popen[str], int]) -> None:
    _, port = sim_process
    bus = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
    listener = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
    network = canopen.Network(bus)
    network.connect()
    try:
        node = network.add_node(2, str(GENERIC_EDS))
        vendor = node.sdo[0x1018][1].raw
        assert vendor == 0x00524F56
        assert node.sdo[0x6041].raw & 0x4F == 0x40  # switch on disabled
        node.sdo[0x1017].raw = 50  # heartbeat on
        node.nmt.state = "OPERATIONAL"
        # a heartbeat sent before the command was processed may still be in flight: the next ones say it
        wait_for(lambda: node.nmt.wait_for_heartbeat(timeout=1.0) == "OPERATIONAL", 10.0, "an OPERATIONAL heartbeat")
        drain(listener, 0.05)
        node.sdo[0x6040].raw = 0x06  # shutdown: the statusword changes, event TPDO1 goes out
        frames = drain(listener, 0.3)
        ids = {m.arbitration_id for m in frames}
        assert 0x702 in ids  # heartbeat
        tpdo1 = [m for m in frames if m.arbitration_id == 0x182]  # default map: statusword
        assert tpdo1 and int.from_bytes(tpdo1[-1].data[:2], "little") & 0x6F == 0x21  # ready to switch on
    finally:
        network.disconnect()
        listener.shutdown()


def test_sim_refuses_a_non_loopback_bind_without_the_flag() -> None:
    result = subprocess.run(rovercan("sim", "--host", "0.0.0.0", "--port", "0"), cwd=REPO,
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 2  # a refusal before anything ran: bad usage
    assert "listens on loopback" in result.stderr


@requires_ros
def test_demo_runs_and_exits_zero() -> None:
    """The demo as a user runs it: its process real-time where this one may be (as the deployed
    node: an ordinary one held past the drive's host timeout on a busy runner makes the drive
    stop itself, and the demo then fails, saying so)."""
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROVERCAN_REALTIME")}
    result = subprocess.run(rovercan("demo", "--duration", "3", "--print-period", "0.5"), cwd=REPO,
                            capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    lines = [ln for ln in result.stdout.splitlines() if ln.startswith("cmd ")]
    assert len(lines) >= 4
    assert "OPERATION_ENABLED" in lines[-1]
    assert "rovercan demo: done" in result.stdout
    assert "ROS discovery LOCALHOST" in result.stdout  # its graph never multicasts beyond loopback
    assert (f"SCHED_FIFO {DRIVER_PRIORITY}" if realtime_allowed() else "ordinary scheduling") in result.stdout.splitlines()[0]


# the demo's end verdict (the drive's verdict, not MotorState's flags): tests/test_services_verdict_reads.py


def test_sim_on_a_kernel_interface_reports_why_it_cannot() -> None:
    from .conftest import kernel_can_available
    reason = kernel_can_available()
    if reason is None:
        pytest.skip("this kernel has vcan0: covered by test_faults' socketcan tier")
    result = subprocess.run(rovercan("sim", "--bus-interface", "socketcan", "--bus-channel", "vcan0"), cwd=REPO,
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 1
    assert "cannot open socketcan vcan0" in result.stderr


def test_sim_on_a_bus_serves_the_drives_of_that_config_bus_only() -> None:
    """config/rover.yaml has node ids 1-3 on can0 and again on can1: put on one python-can bus
    (here a socketcand channel of the emulator), only that bus's three drives answer, once each;
    asked for a channel no config bus has, it is refused and the buses are named."""
    from virtual_can import SimService

    config = str(REPO / "config" / "rover.yaml")
    with SimService([], port=0, extra_channels=("can1",)) as server:
        refused = subprocess.run(rovercan("sim", "--config", config, "--bus-interface", "socketcand",
                                          "--bus-channel", "vcan7", "--bus-kwargs", "host=127.0.0.1",
                                          f"port={server.port}"),
                                 cwd=REPO, capture_output=True, text=True, timeout=30)
        assert refused.returncode == 2, refused.stderr
        assert "can0 (channel can0), can1 (channel can1)" in refused.stderr and "'vcan7'" in refused.stderr
        proc = subprocess.Popen(rovercan("sim", "--config", config, "--bus-interface", "socketcand",
                                         "--bus-channel", "can1", "--bus-kwargs", "host=127.0.0.1",
                                         f"port={server.port}"),
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            first = proc.stdout.readline()
            assert "3 simulated drive(s)" in first and "wheel_front_right" in first, first
            assert "left" not in first, first
            with can.Bus(interface="socketcand", channel="can1", host="127.0.0.1", port=server.port) as bus:
                bus.send(can.Message(arbitration_id=0x000, data=[0x81, 0], is_extended_id=False))  # reset all
                boot_ups: list[int] = []
                deadline = time.monotonic() + 5.0
                while time.monotonic() < deadline:
                    msg = bus.recv(0.2)
                    if msg is not None and 0x701 <= msg.arbitration_id <= 0x77F and bytes(msg.data) == b"\x00":
                        boot_ups.append(msg.arbitration_id - 0x700)
                    if len(boot_ups) >= 3:
                        deadline = min(deadline, time.monotonic() + 0.5)  # a second drive per id would come now
            assert sorted(boot_ups) == [1, 2, 3], boot_ups
        finally:
            stop_process(proc)


def test_drive_processes_serve_the_rover_and_a_dead_one_stops_the_twin(tmp_path: Path) -> None:
    """`rovercan sim --config rover.yaml --drive-processes`: the server here, each bus's drives in a
    process of their own (issue 43: its SYNC timer waits for no drive model). The driver boots and
    enables all six wheels through it; a drive process killed stops the twin with exit 1, naming
    its channel (a twin with drives missing is not the rover's)."""
    from can_config import load_config, with_bus_overrides
    from motor_driver import MotorDriver

    port = free_port()
    proc = subprocess.Popen(rovercan("sim", "--config", str(REPO / "config" / "rover.yaml"), "--drive-processes",
                                     "--port", str(port)), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert "6 simulated drive(s) on can0, can1 (each bus's drives in a process of their own)" in first, \
            first + (proc.stderr.read() if proc.poll() is not None and proc.stderr else "")
        children = [int(p) for p in subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                                                    text=True).stdout.split()]
        assert len(children) == 2, children
        config = with_bus_overrides(load_config(REPO / "config" / "rover.yaml"), host="127.0.0.1", port=port)
        with MotorDriver(config) as driver:
            driver.start()
            for drive in driver:
                drive.enable()
            assert all(d.snapshot().verdict.usable for d in driver)
        os.kill(children[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 1 and "the simulated drives of channel can" in err and "exited (-9)" in err, err
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(("args", "says"), [
    (["--drives", "2"], "--drive-processes: give --config"),
    (["--config", "config/rover.yaml", "--status-period", "1"], "need the drives in the server's process")])
def test_drive_processes_are_refused_where_they_cannot_serve(args: list[str], says: str) -> None:
    done = subprocess.run(rovercan("sim", "--drive-processes", "--port", "0", *args), cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2 and says in done.stderr and "Traceback" not in done.stderr, done.stderr

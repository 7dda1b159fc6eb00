"""The kernel tier on a real CAN controller driver (issue 42): QEMU's emulated SJA1000 pair
(kvaser_pci, the kernel's sja1000 driver) on one emulated bus, can0 and can1 in the kernel tier's
VM. vcan has no controller; these have a bitrate, a state and error counters, read back here
through rtnetlink as `rovercan bus-health` reads them on the Orin. QEMU's SJA1000 sees a
perfect bus, so the error states are fed to the decoder instead (tests/test_bus_health.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import can
import pytest

from rovercan.cli import main

from .conftest import REPO, kernel_controllers_available

HANG_S = 120.0  # a hang, not a timing claim (the VM's Python is about 12x slower)


pytestmark = [pytest.mark.kernel, pytest.mark.skipif(kernel_controllers_available() is not None,
                                                         reason=str(kernel_controllers_available()))]


def rovercan(*args: str) -> subprocess.CompletedProcess[str]:
    """The command as a user runs it: its own process (5-15 s to start in the VM)."""
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=HANG_S)


def rovercan_here(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """The same command's code in this process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_can_up_sets_the_controller_and_bus_health_reads_it_back_error_active(capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("can0", "can1"):
        code, _, err = rovercan_here(capsys, "can-up", name, "--bitrate", "1000000", "--restart-ms", "100")
        assert code == 0, err
    health = rovercan("bus-health", "-i", "socketcan", "-c", "can0", "--json")
    assert health.returncode == 0, health.stderr
    row = json.loads(health.stdout)
    assert (row["kind"], row["state"], row["bitrate"], row["restart_ms"]) == ("can", "ERROR-ACTIVE", 1000000, 100)
    assert (row["tx_errors"], row["rx_errors"]) == (0, 0) and row["link_up"] is True
    # one emulated bus: a frame sent by one controller is received by the other
    with can.Bus(interface="socketcan", channel="can1") as rx, can.Bus(interface="socketcan", channel="can0") as tx:
        tx.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        msg = rx.recv(HANG_S)
    assert msg is not None and msg.arbitration_id == 0x123 and bytes(msg.data) == b"\x01\x02"


def test_a_controller_that_is_down_is_reported_with_what_to_do(capsys: pytest.CaptureFixture[str]) -> None:
    assert rovercan_here(capsys, "can-up", "can1", "--bitrate", "500000")[0] == 0
    subprocess.run(["ip", "link", "set", "can1", "down"], check=True, timeout=HANG_S)
    try:
        code, out, err = rovercan_here(capsys, "bus-health", "-i", "socketcan", "-c", "can1", "--json")
        assert code == 1 and "can1 is down" in err and "can-up" in err
        row = json.loads(out)
        assert row["link_up"] is False and row["bitrate"] == 500000  # what it was set to, though down
    finally:
        assert rovercan_here(capsys, "can-up", "can1", "--bitrate", "1000000")[0] == 0

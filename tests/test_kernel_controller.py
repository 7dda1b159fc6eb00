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

from .conftest import KERNEL_TIER_COMMAND, REPO, kernel_can_available

HANG_S = 120.0  # a hang, not a timing claim (the VM's Python is about 12x slower)


def controllers_here() -> str | None:
    """None when can0 and can1 are CAN controllers here, else why not."""
    if (why := kernel_can_available("vcan0")) is not None:
        return why
    try:
        from motor_driver.bushealth import read_kernel_health

        kinds = [read_kernel_health(name).kind for name in ("can0", "can1")]
    except Exception as err:
        return f"no CAN controllers can0 and can1 here ({err}); `{KERNEL_TIER_COMMAND}` runs a VM with an SJA1000 pair"
    if kinds != ["can", "can"]:
        return f"can0 and can1 are {kinds}, not CAN controllers; `{KERNEL_TIER_COMMAND}` runs a VM with an SJA1000 pair"
    return None


pytestmark = [pytest.mark.kernel, pytest.mark.skipif(controllers_here() is not None, reason=str(controllers_here()))]


def rovercan(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=HANG_S)


def test_can_up_sets_the_controller_and_bus_health_reads_it_back_error_active() -> None:
    for name in ("can0", "can1"):
        up = rovercan("can-up", name, "--bitrate", "1000000", "--restart-ms", "100")
        assert up.returncode == 0, up.stderr
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


def test_a_controller_that_is_down_is_reported_with_what_to_do() -> None:
    assert rovercan("can-up", "can1", "--bitrate", "500000").returncode == 0
    subprocess.run(["ip", "link", "set", "can1", "down"], check=True, timeout=HANG_S)
    try:
        health = rovercan("bus-health", "-i", "socketcan", "-c", "can1", "--json")
        assert health.returncode == 1 and "can1 is down" in health.stderr and "can-up" in health.stderr
        row = json.loads(health.stdout)
        assert row["link_up"] is False and row["bitrate"] == 500000  # what it was set to, though down
    finally:
        assert rovercan("can-up", "can1", "--bitrate", "1000000").returncode == 0

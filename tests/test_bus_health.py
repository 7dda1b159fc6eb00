"""The kernel's view of a bus, decoded (motor_driver.bus.link): rtnetlink link messages as the
kernel sends them, built and encoded with pyroute2, then decoded as the driver reads them.
Every state is fed here, also those an emulated controller never reaches (QEMU's SJA1000 sees a
perfect bus); the kernel tier reads a real controller driver's (tests/test_kernel_tier.py)."""

from __future__ import annotations

import struct
import subprocess
import sys
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motor_driver.bus.link import RISING, STATES, XSTATS_FIELDS, KernelBusHealth, health_from_link, rising
from motor_driver.diagnostics.health import ERROR, OK, WARN, bus_health

from .conftest import REPO

pyroute2 = pytest.importorskip("pyroute2", reason="pyroute2 is Linux only")
from pyroute2.netlink.rtnl.ifinfmsg import ifinfmsg  # noqa: E402

IFF_UP = 0x1


#: A controller at 1 Mbit/s, ERROR-ACTIVE, restart-ms 100, every counter 0: what link() sends unless told.
LINK = {"kind": "can", "up": True, "state": 0, "txerr": 0, "rxerr": 0, "bitrate": 1_000_000, "sample_point": 875,
        "restart_ms": 100, "counters": (0, 0, 0, 0, 0, 0), "dropped": (0, 0)}


def link(name: str = "can0", **fields: Any) -> object:
    """One RTM_NEWLINK message as the kernel sends it for a CAN interface (LINK, as ``fields`` say
    otherwise), encoded and decoded."""
    f = {**LINK, **fields}
    kind, up, state, txerr, rxerr = f["kind"], f["up"], f["state"], f["txerr"], f["rxerr"]
    bitrate, sample_point, restart_ms, counters, dropped = (f["bitrate"], f["sample_point"], f["restart_ms"],
                                                             f["counters"], f["dropped"])
    data = [("IFLA_CAN_STATE", state), ("IFLA_CAN_RESTART_MS", restart_ms),
            ("IFLA_CAN_BERR_COUNTER", {"txerr": txerr, "rxerr": rxerr}),
            ("IFLA_CAN_BITTIMING", {"bitrate": bitrate, "sample_point": sample_point, "tq": 125, "prop_seg": 2,
                                    "phase_seg1": 3, "phase_seg2": 2, "sjw": 1, "brp": 1})]
    info: list[tuple[str, object]] = [("IFLA_INFO_KIND", kind)]
    if kind == "can":
        info += [("IFLA_INFO_DATA", {"attrs": data}), ("IFLA_INFO_XSTATS", struct.pack("<6I", *counters))]
    msg = ifinfmsg()
    msg["index"], msg["flags"] = 3, IFF_UP if up else 0
    msg["attrs"] = [("IFLA_IFNAME", name), ("IFLA_OPERSTATE", "UP" if up else "DOWN"),
                    ("IFLA_LINKINFO", {"attrs": info}),
                    ("IFLA_STATS64", {"rx_dropped": dropped[0], "tx_dropped": dropped[1]})]
    msg.encode()
    decoded = ifinfmsg(msg.data)
    decoded.decode()
    return decoded


def test_an_error_active_controller_at_1_mbit() -> None:
    health = health_from_link(link(counters=(1, 2, 3, 4, 5, 6), dropped=(7, 8)))
    assert health.ok and health.problems() == []
    assert (health.state, health.bitrate, health.sample_point, health.restart_ms) == ("ERROR-ACTIVE", 1_000_000, 0.875, 100)
    assert [getattr(health, f) for f in XSTATS_FIELDS] == [1, 2, 3, 4, 5, 6]
    assert (health.rx_dropped, health.tx_dropped) == (7, 8)


@pytest.mark.parametrize(("state", "name", "advice"), [
    (1, "ERROR-WARNING", "check termination"), (2, "ERROR-PASSIVE", "check termination and bitrate"),
    (3, "BUS-OFF", "restart-ms")])
def test_every_other_state_is_a_problem_that_says_what_to_do(state: int, name: str, advice: str) -> None:
    health = health_from_link(link(state=state, txerr=130, rxerr=127))
    assert not health.ok and health.state == name and (health.tx_errors, health.rx_errors) == (130, 127)
    assert any(name in p and advice in p for p in health.problems()), health.problems()


def test_a_link_down_and_restart_ms_0_are_said() -> None:
    down = health_from_link(link(up=False, state=4))
    assert not down.ok and any("is down" in p and "can-up" in p for p in down.problems())
    no_restart = health_from_link(link(restart_ms=0))
    assert any("restart-ms 0" in p for p in no_restart.problems())


def test_a_vcan_has_no_controller_and_nothing_is_guessed() -> None:
    health = health_from_link(link("vcan0", kind="vcan"))
    assert health.ok and health.state is None and health.bitrate is None and health.tx_errors is None


@given(state=st.integers(0, 5), txerr=st.integers(0, 255), rxerr=st.integers(0, 255),
       counters=st.tuples(*[st.integers(0, 2**32 - 1)] * 6), bitrate=st.integers(10_000, 1_000_000))
def test_whatever_the_kernel_says_is_decoded_as_said(state: int, txerr: int, rxerr: int, counters: tuple[int, ...],
                                                     bitrate: int) -> None:
    health = health_from_link(link(state=state, txerr=txerr, rxerr=rxerr, counters=counters, bitrate=bitrate))
    assert health.state == list(STATES.values())[state]
    assert (health.tx_errors, health.rx_errors, health.bitrate) == (txerr, rxerr, bitrate)
    assert tuple(getattr(health, f) for f in XSTATS_FIELDS) == counters
    assert health.ok == (state == 0)


def test_bus_health_of_a_bus_that_is_no_kernel_interface_says_unknown() -> None:
    run = subprocess.run([sys.executable, "-m", "rovercan", "bus-health", "--config", str(REPO / "config" / "rover.yaml"),
                          "-c", "can1", "--json"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert '"state": "unknown"' in run.stdout and '"channel": "can1"' in run.stdout


@pytest.mark.parametrize(("fields", "level", "words"), [
    ({}, OK, "ERROR-ACTIVE"), ({"state": 1}, WARN, "check termination"), ({"state": 2}, WARN, "ERROR-PASSIVE"),
    ({"state": 3}, ERROR, "BUS-OFF"), ({"up": False, "state": 4}, ERROR, "is down")])
def test_a_bus_status_carries_the_kernels_state_and_counters(fields: dict[str, object], level: int, words: str) -> None:
    """What /diagnostics publishes for each bus (nodes/rover_driver.py turns it into a DiagnosticStatus)."""
    kernel = health_from_link(link(txerr=97, rxerr=3, counters=(10, 2, 1, 0, 0, 1), **fields))
    health = bus_health(load=0.2, lost=False, frames=1000, error_frames=4, kernel=kernel)
    assert health.level == level and words in health.message, health
    assert {k: health.values[k] for k in ("tx_errors", "rx_errors", "bitrate", "restarts", "error_passive")} == {
        "tx_errors": "97", "rx_errors": "3", "bitrate": "1000000", "restarts": "1", "error_passive": "1"}
    assert health.values["can_state"] == kernel.state


def test_a_bus_status_without_a_kernel_controller_says_unknown_and_lost_wins() -> None:
    unknown = bus_health(load=0.7, lost=False, frames=1, error_frames=0, kernel=None, why_unknown="socketcand")
    assert unknown.level == WARN and unknown.values["can_state"] == "unknown (socketcand)"  # the load warns
    assert bus_health(load=0.1, lost=True, frames=1, error_frames=0, kernel=None).level == ERROR
    vcan = bus_health(load=0.1, lost=False, frames=1, error_frames=0, kernel=health_from_link(link("vcan0", kind="vcan")))
    assert vcan.level == OK and vcan.values["can_state"] == "none (no controller)"


@given(st.sampled_from(sorted(RISING)), st.integers(0, 2**31), st.integers(1, 1000))
def test_a_counter_that_rose_between_two_reads_is_named_with_what_to_do(counter: str, start: int, rise: int) -> None:
    """rising(): every error and drop counter the kernel has, compared between two reads; one that
    went down (an error counter recovering) or stayed is no problem."""
    fields = {"txerr": "tx_errors", "rxerr": "rx_errors"}
    def read(value: int) -> KernelBusHealth:
        if counter in fields.values():
            key = next(k for k, v in fields.items() if v == counter)
            return health_from_link(link(**{key: min(value, 255)}))
        if counter in XSTATS_FIELDS:
            return health_from_link(link(counters=tuple(value if n == counter else 0 for n in XSTATS_FIELDS)))
        return health_from_link(link(dropped=(value, 0) if counter == "rx_dropped" else (0, value)))
    low, high = (min(start, 254), min(start, 254) + 1) if counter in fields.values() else (start, start + rise)
    said = rising(read(low), read(high), 2.0)
    assert len(said) == 1 and counter in said[0] and f"{low} -> {high}" in said[0] and RISING[counter] in said[0]
    assert rising(read(high), read(low), 2.0) == [] and rising(read(low), read(low), 2.0) == []


def test_a_vcan_has_no_counters_to_rise() -> None:
    vcan = health_from_link(link("vcan0", kind="vcan"))
    assert rising(vcan, vcan, 1.0) == []


def test_frames_given_up_for_a_full_transmit_queue_warn_and_say_what_to_do() -> None:
    kernel = health_from_link(link())
    counted = bus_health(load=0.1, lost=False, frames=10, error_frames=0, kernel=kernel, tx_queue_full=3)
    assert counted.level == OK and counted.values["tx_queue_full"] == "3"  # retried and sent: counted only
    dropped = bus_health(load=0.1, lost=False, frames=10, error_frames=0, kernel=kernel, tx_queue_full=9, tx_not_sent=2)
    assert dropped.level == WARN and "2 frame(s) not sent" in dropped.message and "termination" in dropped.message


@pytest.mark.parametrize(("fields", "says"), [
    ({"up": False}, "link down (can0 is down)"),
    ({"state": 3}, "can0 is BUS-OFF; the kernel restarts it after restart-ms 100"),
    ({"state": 3, "restart_ms": 0}, "restart-ms is 0: it stays off until `ip link set can0 type can restart`")])
def test_the_driver_waits_for_a_link_that_is_down_or_bus_off_and_says_so_once(
        fields: dict[str, object], says: str, caplog: pytest.LogCaptureFixture) -> None:
    """The supervisor's wait for a lost kernel bus (motor_driver.runtime.supervise_bus: _link_down, _link_said), fed the
    kernel's link messages (QEMU's SJA1000 never goes BUS-OFF; the kernel tier takes a real one
    down): not ready while down or BUS-OFF, said once with what to do, and once when it is back."""
    import can

    from can_config import parse_config
    from motor_driver import MotorDriver

    config = parse_config({"buses": [{"name": "can0", "interface": "socketcan", "channel": "can0"}],
                           "drives": [{"name": "m", "node_id": 1}]})
    with can.Bus(interface="virtual", channel="link-test") as bus, MotorDriver(config, {"can0": bus}) as driver:
        reads = [health_from_link(link(**fields))] * 3 + [health_from_link(link())]
        buses = driver.supervisor.bus  # the worker asks (_link_down), the supervisor says (_link_said)
        buses.kernel_health = lambda name: (reads.pop(0), "")  # type: ignore[method-assign]
        ready = []
        for _ in range(4):
            why = buses._link_down("can0")
            ready.append(not why)
            buses._link_said("can0", buses.bus_records["can0"], why)
        assert ready == [False, False, False, True]
    said = [r.getMessage() for r in caplog.records if "bus can0: link" in r.getMessage()]
    assert len(said) == 2 and says in said[0] and "left disabled" in said[0] and "link up again" in said[1], said

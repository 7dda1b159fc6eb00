"""The driver's own SYNC on a kernel bus: SocketCAN loops the kernel broadcast manager's frames
back to the driver's raw socket, marked as made on this host (``is_rx`` False). They are judged by
their rate; more SYNC than the driver's period gives, or any SYNC from another host, is another
master. (The kernel tier runs the same path on a real vcan0; this is its pure part, frame by frame.)"""

from __future__ import annotations

import can

from motor_driver.runtime.driver import ForeignTraffic, is_kernel_bus

PERIOD_S = 0.01


def sync(t: float, *, from_this_host: bool = True) -> can.Message:
    return can.Message(arbitration_id=0x080, data=b"", is_extended_id=False, timestamp=t, is_rx=not from_this_host)


def kernel_listener() -> ForeignTraffic:
    foreign = ForeignTraffic(127, [1, 2])
    foreign.marks_local_frames = True
    foreign.own_sync_period_s = PERIOD_S  # as BusHandle.start_sync sets it for the kernel's BCM
    return foreign


def test_the_drivers_own_bcm_sync_is_never_another_master() -> None:
    foreign = kernel_listener()
    for i in range(500):  # five seconds of its own SYNC, with the kernel's jitter
        foreign.on_message_received(sync(100.0 + i * PERIOD_S + (0.002 if i % 7 == 0 else 0.0)))
    assert foreign.evidence(1, 0.0) == ""


def test_a_second_driver_on_the_same_host_is_noticed_within_one_second() -> None:
    foreign = kernel_listener()
    t = 100.0
    for i in range(100):  # both drivers' SYNC interleaved, each at its own period
        foreign.on_message_received(sync(t + i * PERIOD_S))
        foreign.on_message_received(sync(t + i * PERIOD_S + 0.004))
        if foreign.evidence(1, 0.0):
            break
    assert "SYNC frames this driver did not send" in foreign.evidence(1, 0.0)
    assert i * PERIOD_S < 1.0


def test_the_drivers_own_sync_bunched_after_a_stall_is_not_another_master() -> None:
    """A stalled host delivers its own SYNCs late and together: 0.5 s of nothing, then the fifty
    the broadcast manager sent meanwhile within 25 ms of each other (their receive timestamps).
    Counted over the window, that is still its own rate (over 0.3 s it was not)."""
    foreign = kernel_listener()
    t = 100.0
    for i in range(100):
        foreign.on_message_received(sync(t + i * PERIOD_S))
    t += 100 * PERIOD_S + 0.5
    for i in range(50):
        foreign.on_message_received(sync(t + i * 0.0005))
    for i in range(1, 100):
        foreign.on_message_received(sync(t + 0.025 + i * PERIOD_S))
    assert foreign.evidence(1, 0.0) == ""


def test_one_sync_from_another_host_is_another_master() -> None:
    foreign = kernel_listener()
    foreign.on_message_received(sync(100.0, from_this_host=False))
    assert "SYNC frames this driver did not send" in foreign.evidence(1, 0.0)


def test_a_socketcand_bus_is_not_taken_for_a_kernel_bus() -> None:
    """socketcand frames say nothing of their origin (python-can leaves is_rx True): there only
    the rate counts."""
    with can.Bus(interface="virtual", channel="rovercan-kernel-check") as bus:
        assert not is_kernel_bus(bus)

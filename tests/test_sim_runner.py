"""Tier 1: the drive simulator's runner loses no frame of a burst longer than one tick's bound."""

from __future__ import annotations

import threading

import can

from can_config import GENERIC_EDS, load_drive_od
from virtual_can.sim import SimulatedDrive
from virtual_can.sim.runner import MAX_FRAMES_PER_TICK, DriveSimulator

READ_DEVICE_TYPE = bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])  # SDO upload 0x1000:0
READ_VENDOR_ID = bytes([0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0])  # SDO upload 0x1018:1: the end marker


def test_a_burst_beyond_one_tick_s_bound_has_every_frame_handled() -> None:
    """A runner held between a look at the bus and its handling (a starved thread) finds more frames
    queued than it handles before the drives' time moves on (MAX_FRAMES_PER_TICK): the one it read
    past that bound was dropped, so an SDO request among them went unanswered (a drive process of
    18 drives at 100 Hz failed a driver's boot that way). Each request is answered; the marker sent
    last, answered after them, shows the listener heard all that came."""
    sim_bus = can.Bus(interface="virtual", channel="runner-burst")
    peer = can.Bus(interface="virtual", channel="runner-burst")
    held, release = threading.Event(), threading.Event()

    def hook(point: str) -> None:
        if point == "looked" and not release.is_set():
            held.set()
            release.wait(60.0)

    runner = DriveSimulator(sim_bus, [SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))], realtime=False)
    runner.set_hook(hook)
    try:
        with runner:
            assert held.wait(60.0), "the runner never looked at the bus"
            burst = MAX_FRAMES_PER_TICK + 10
            for _ in range(burst):
                peer.send(can.Message(arbitration_id=0x601, data=READ_DEVICE_TYPE, is_extended_id=False))
            release.set()
            peer.send(can.Message(arbitration_id=0x601, data=READ_VENDOR_ID, is_extended_id=False))
            answered = 0
            while True:
                msg = peer.recv(60.0)
                assert msg is not None, f"no answer to the marker ({answered} of {burst} answered before)"
                if msg.arbitration_id != 0x581:
                    continue
                if msg.data[1:4] == READ_VENDOR_ID[1:4]:
                    break
                answered += 1
            assert answered == burst, f"{burst - answered} of {burst} SDO requests went unanswered"
    finally:
        peer.shutdown()
        sim_bus.shutdown()

"""The driver's per-frame and per-command paths, each timed alone (CPU of the calling thread, not
wall time: a busy machine slows it less): ``python benchmarks/hotpath.py [N]``.

One drive of config/rover.yaml, booted on the simulator (``rovercan sim --drive-processes``), enabled and streaming in CSP; then, each
``N`` times and the best of three rounds: a TPDO through the bus's dispatch (``GuardedNetwork.notify``
into the state cache: what the receive thread does per frame), a snapshot (what every publisher,
the drive system and diagnostics read; ``snapshot_us`` of one already judged, ``tpdo_then_snapshot_us``
a TPDO dispatched and then judged anew, each reader's first look after a SYNC), the verdict alone, and a streamed set-point (the command
path, its RPDO sent); and a frame through every listener of the bus's receive thread (what
python-can's Notifier does with a frame it read); and a read of socketcand text through the bus's
receive path into the caches (``batch_frame_us``, per frame: three rounds of the drive's TPDOs in
one read, parsed and dispatched as the commit under test does it, the read included); and the
flight recorder's keeping of one frame alone, a TPDO received (``recorder_received_us``, per
frame of a read of three rounds of the drive's TPDOs, as the batch read hands them to its receive
tap) and an RPDO sent (``recorder_sent_us``, as canopen's send hands it over), each into the bus's live ring.
Prints microseconds per call as JSON. Used to A/B a change against the last commit (the same
script on both, one machine, one run each: their ratio is the figure).
"""

from __future__ import annotations

import dataclasses
import json
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import can

from can_config import load_config, with_bus_overrides
from motor_driver import MotorDriver

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stack_run

REPO = Path(__file__).resolve().parent.parent
ROVER = REPO / "config" / "rover.yaml"


#: calls timed in a row; then a pause (no CPU: not counted) lets the driver's other threads run,
#: so the host heartbeat goes out on time on a busy machine and the drive does not stop itself
CHUNK = 100
PAUSE_S = 0.005


def per_call_us(fn: Callable[[], object], n: int, rounds: int = 3) -> float:
    best = float("inf")
    for _ in range(rounds):
        spent = 0.0
        for _ in range(max(1, n // CHUNK)):
            t0 = time.thread_time()
            for _ in range(CHUNK):
                fn()
            spent += time.thread_time() - t0
            time.sleep(PAUSE_S)
        best = min(best, spent)
    return round(best / (max(1, n // CHUNK) * CHUNK) * 1e6, 2)


def batch_path(handle: object, notifier: can.Notifier, layouts: list[tuple[int, bytes]]) -> tuple[Callable[[], object], int]:
    """One read of three rounds of the drive's TPDOs (a bus of three such drives),
    written to a socket pair and read by a socketcand bus wired as the driver wires it (its read,
    parse and dispatch: the batch sink where the commit has one, else python-can's recv a frame at
    a time through the Notifier's listeners, as its thread does); and the frames per read."""
    from can.interfaces.socketcand.socketcand import SocketCanDaemonBus

    from motor_driver.bus import adapters

    ours, peer = socket.socketpair()
    bus = SocketCanDaemonBus.__new__(SocketCanDaemonBus)
    for name, value in ((adapters.SOCKETCAND_SOCKET_ATTRIBUTE, ours), (adapters.SOCKETCAND_TCP_TUNE, False),
                        (adapters.SOCKETCAND_BUFFERS[0], []), (adapters.SOCKETCAND_BUFFERS[1], "")):
        setattr(bus, name, value)
    bus._filters, bus.channel = None, "bench"
    adapters.batch_receive(bus)
    stamp = time.time()
    # no SYNC among them: one every call would be another master's SYNC, refusing the commands
    text = "".join(f"< frame {cob:03X} {stamp:.6f} {data.hex().upper()} >" for _ in range(3) for cob, data in layouts)
    chunk = text.encode("ascii")
    frames = 3 * len(layouts)
    sink = getattr(getattr(handle, "dispatch", None), "on_frames", None)
    if sink is not None and getattr(adapters, "dispatch_batches", None) is not None:
        adapters.dispatch_batches(bus, sink)

        def read() -> None:
            peer.sendall(chunk)
            bus.recv(0)
    else:
        def read() -> None:
            peer.sendall(chunk)
            while (msg := bus.recv(0)) is not None:
                with notifier._lock:
                    notifier._on_message_received(msg)
    return read, frames


def measure(n: int) -> dict[str, float]:
    config = load_config(ROVER)
    # a busy machine starves the simulator now and then: data late by 0.2 s would refuse the
    # set-points measured (a refusal costs less); the staleness bound is not what is timed here
    config = dataclasses.replace(config, drives=tuple(dataclasses.replace(d, stale_after_syncs=1000)
                                                      for d in config.drives))
    # the simulator in processes of its own (as the stack run has it): in this process its drive
    # models would wait for the interpreter behind the loops timed here, and on a busy machine
    # miss the host heartbeat and stop themselves
    with stack_run.simulator("--config", str(ROVER), "--drive-processes") as port:
        cfg = with_bus_overrides(config, host="127.0.0.1", port=port)
        with MotorDriver(cfg) as driver:
            driver.start()
            drive = next(iter(driver))
            drive.enable()
            angle = drive.snapshot().angle_deg
            drive.stream_position(angle)  # the switch to CSP (waits), then set-points at once
            layout = next(iter(drive.cache._layouts.values()))
            rx = drive.cache.received
            fields = {0x6041: rx.statusword, 0x6064: rx.position_counts, 0x606C: 0, 0x6077: 0, 0x6061: rx.mode}
            data = bytearray(layout.codec.pack(*(fields.get(i, 0) for i in layout.indexes)))
            network = drive.network
            cob = layout.cob_id

            def frame() -> None:
                network.notify(cob, data, time.time())

            notifier = network.notifier
            msg = can.Message(arbitration_id=cob, data=data, is_extended_id=False, timestamp=time.time())

            def received() -> None:  # what python-can's Notifier does per frame, after its recv
                notifier._on_message_received(msg)

            layouts = [(cob_id, bytes(bytearray(lay.codec.pack(*(fields.get(i, 0) for i in lay.indexes)))))
                       for cob_id, lay in drive.cache._layouts.items()]
            read, per_read = batch_path(driver.buses[drive.config.bus], notifier, layouts)
            recorder = driver.recorder
            assert recorder is not None, "config/rover.yaml's recorder is on"
            tap, bus_name, rpdo = recorder.listener(drive.config.bus), drive.config.bus, bytes(8)

            on_read = getattr(tap, "on_read", None)
            read_frames = [(cob_id, bytearray(frame_data), time.time(), 0) for cob_id, frame_data in layouts] * 3

            def kept_received() -> None:  # one read's frames (a frame a call where the commit has no on_read)
                if on_read is not None:
                    on_read(read_frames)
                else:
                    for cob_id, frame_data, stamp, flags in read_frames:
                        tap.on_frame(stamp, cob_id, flags, frame_data)

            def kept_sent() -> None:
                recorder.record_frame(bus_name, 0x201, rpdo)
            # the command first: a round of the others holds the interpreter long enough on a busy
            # machine for the drive's host watch to stop it
            out = {"stream_setpoint_us": per_call_us(lambda: drive.stream_position(angle, at_once=True), n),
                   "verdict_us": per_call_us(drive.verdict, n),
                   "snapshot_us": per_call_us(drive.snapshot, n),
                   "tpdo_dispatch_us": per_call_us(frame, n),
                   # a TPDO, then a snapshot of it: judged anew, as each reader's first look after a SYNC
                   "tpdo_then_snapshot_us": per_call_us(lambda: (frame(), drive.snapshot()), n),
                   "frame_received_us": per_call_us(received, n),
                   "batch_frame_us": round(per_call_us(read, max(CHUNK, n // per_read)) / per_read, 2),
                   "recorder_received_us": round(per_call_us(kept_received, max(CHUNK, n // len(read_frames)))
                                                 / len(read_frames), 2),
                   "recorder_sent_us": per_call_us(kept_sent, n)}
    return out


def main() -> int:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 5000
    print(json.dumps(measure(n)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

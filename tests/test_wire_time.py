"""Wire-time mode of the emulator: frames take their bit time (worst-case stuffing), contend by
identifier, and the channel reports its load. At 10 kbit/s an 8-byte frame holds the wire for
about 13 ms, long enough to queue contenders behind it from Python deterministically."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest

from virtual_can import BusEngine, VirtualBus
from virtual_can.wire import frame_time_s

BITRATE = 10_000


@pytest.fixture
def engine() -> Iterator[BusEngine]:
    with BusEngine(bitrate=BITRATE, wire_time=True) as eng:
        yield eng


def frame(can_id: int) -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes(8), is_extended_id=False)


def test_lower_identifier_wins_arbitration(engine: BusEngine) -> None:
    with VirtualBus("can0", engine=engine) as a, VirtualBus("can0", engine=engine) as b, \
            VirtualBus("can0", engine=engine) as rx:
        a.send(frame(0x700))  # on the wire for ~13 ms: the others queue behind it
        a.send(frame(0x300))
        b.send(frame(0x100))
        a.send(frame(0x200))
        got = [rx.recv(1.0) for _ in range(4)]
    assert [m.arbitration_id for m in got if m is not None] == [0x700, 0x100, 0x200, 0x300]


def test_frames_take_their_bit_time_and_the_load_is_reported(engine: BusEngine) -> None:
    duration = frame_time_s(8, BITRATE, extended=False)
    assert duration == pytest.approx(135 / BITRATE)  # 8-byte standard frame, worst-case stuffing
    channel = engine.channel("can0")
    with VirtualBus("can0", engine=engine) as tx, VirtualBus("can0", engine=engine) as rx:
        channel.reset_stats()
        for i in range(10):
            tx.send(frame(0x181 + i))
        got = [rx.recv(1.0) for _ in range(10)]
        load = channel.load()
    stamps = [m.timestamp for m in got if m is not None]
    assert len(stamps) == 10
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    # stamped at their end of frame: back to back, one frame time apart, never closer
    assert min(gaps) >= duration * 0.999 and max(gaps) < duration * 1.5, gaps
    assert channel.stats.busy_s == pytest.approx(10 * duration)
    assert 0.5 < load <= 1.0  # a flooded wire: busy most of the time since the reset

"""Frames lost, measured (pure: no I/O, no clock of its own): per drive, the TPDOs it sends every
SYNC expected against those received, and its heartbeats due in the window (:func:`heartbeats_due`)
against those received, over the last ``window_syncs`` SYNC periods.

The SYNCs are those seen on the bus (:class:`motor_driver.bus.traffic.BusStats`: the driver's own
where the bus echoes them, a bus daemon's timer); where a bus shows none, the time elapsed over
the SYNC period stands for them. A SYNC lost on the wire makes no TPDO and is not counted either:
what is measured is the drive's frames lost on their way to this host. Both ends of the window
are read at the same moment, so a steady delay between a SYNC and its TPDOs cancels out.

Owner: one thread feeds and reads an instance (the driver node's diagnostics timer): :meth:`add`
takes the counters each has one writer of (the receive thread's); a drive whose data is not news
(late, lost, re-booting: its verdict) is not measured, and its window starts again.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class Counts:
    """The counters of one drive and its bus, read at one moment."""

    at: float  # when they were read (monotonic, s)
    syncs: int  # SYNC frames seen on the drive's bus
    tpdos: int  # the drive's TPDOs of those it sends every SYNC, received
    heartbeats: int  # its heartbeats received


@dataclass(frozen=True)
class Loss:
    """What a window measured."""

    syncs: int  # SYNC periods it covers
    tpdos_expected: int
    tpdos_received: int
    heartbeats_expected: int = 0
    heartbeats_received: int = 0

    @property
    def tpdo_percent(self) -> float:
        return _percent(self.tpdos_expected, self.tpdos_received)

    @property
    def heartbeat_percent(self) -> float:
        return _percent(self.heartbeats_expected, self.heartbeats_received)

    @property
    def worst_percent(self) -> float:
        return max(self.tpdo_percent, self.heartbeat_percent)

    def text(self) -> str:
        """``TPDOs 31 of 600 lost (5.2 %), heartbeats 1 of 20 (5.0 %) over 200 SYNCs``."""
        lost = max(0, self.tpdos_expected - self.tpdos_received)
        said = f"TPDOs {lost} of {self.tpdos_expected} lost ({self.tpdo_percent:.1f} %)"
        if self.heartbeats_expected:
            hb_lost = max(0, self.heartbeats_expected - self.heartbeats_received)
            said += f", heartbeats {hb_lost} of {self.heartbeats_expected} ({self.heartbeat_percent:.1f} %)"
        return f"{said} over {self.syncs} SYNCs"


def heartbeats_due(elapsed_s: float, period_s: float) -> int:
    """The heartbeats that must have come in any ``elapsed_s`` of a producer of ``period_s``,
    whatever its phase and a jitter under half a period: one fewer than the whole periods (each
    end of the window can cut one). Counting the periods themselves called a window that began
    just after a heartbeat and ended just before one a lost frame (1 of 20: 5 %, a WARN)."""
    return max(0, math.floor(elapsed_s / period_s + 1e-9) - 1)


def _percent(expected: int, received: int) -> float:
    return 100.0 * max(0, expected - received) / expected if expected > 0 else 0.0


def total(losses: Iterable[Loss]) -> Loss | None:
    """Several drives' windows summed (a bus's figure); None when there is none."""
    items = list(losses)
    if not items:
        return None
    return Loss(max(x.syncs for x in items), sum(x.tpdos_expected for x in items),
                sum(x.tpdos_received for x in items), sum(x.heartbeats_expected for x in items),
                sum(x.heartbeats_received for x in items))


class FrameLoss:
    """One drive's frames expected against received over the last ``window_syncs`` SYNC periods."""

    def __init__(self, tpdos_per_sync: int, sync_period_s: float, heartbeat_period_s: float | None,
                 window_syncs: int) -> None:
        self.tpdos_per_sync = tpdos_per_sync
        self.sync_period_s = sync_period_s
        self.heartbeat_period_s = heartbeat_period_s  # None: it sends no heartbeat (guarded)
        self.window_syncs = window_syncs
        self._samples: deque[Counts] = deque()

    def add(self, counts: Counts, measuring: bool = True) -> None:
        """A new reading; ``measuring`` False (its data not news) starts the window again."""
        if not measuring:
            self._samples.clear()
            return
        self._samples.append(counts)
        while len(self._samples) > 2 and self._syncs(self._samples[1], counts) >= self.window_syncs:
            self._samples.popleft()  # the window still spans window_syncs without the oldest

    def _syncs(self, first: Counts, last: Counts) -> float:
        seen = last.syncs - first.syncs
        return seen if seen > 0 else (last.at - first.at) / self.sync_period_s

    def loss(self) -> Loss | None:
        """The window's figures, or None while it spans fewer than ``window_syncs`` SYNC periods."""
        if len(self._samples) < 2:
            return None
        first, last = self._samples[0], self._samples[-1]
        syncs = self._syncs(first, last)
        if syncs < self.window_syncs:
            return None
        hb_expected = heartbeats_due(last.at - first.at, self.heartbeat_period_s) if self.heartbeat_period_s else 0
        return Loss(round(syncs), round(syncs * self.tpdos_per_sync), last.tpdos - first.tpdos, hb_expected,
                    last.heartbeats - first.heartbeats if hb_expected else 0)

    def progress(self) -> str:
        """What a window still measuring says: ``measuring (120 of 500 SYNCs)``."""
        done = self._syncs(self._samples[0], self._samples[-1]) if len(self._samples) > 1 else 0.0
        return f"measuring ({done:.0f} of {self.window_syncs} SYNCs)"

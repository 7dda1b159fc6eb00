"""The frames of several buses as one stream in time order (pure).

Each bus's frames come in its own time order, but a reader per bus hands them over in the order
its thread ran (a live recording), and a log of several buses holds them in that arrival order:
one bus's frames of the last half second can come before the other's of the same half second.
Judged in that order, a drive of the later bus looks silent (its heartbeat "lost" while it was
sent every 100 ms) and SYNC cycles of two buses fall apart.

:class:`TimeMerge` lets a frame out once no bus can still bring an older one: every bus heard
within ``hold_s`` of the newest frame has sent a frame ``SLACK_S`` newer (a bus is in time order
but for frames stamped by two threads of its sender, such as a simulator's drives and its SYNC
timer, which a busy machine hands over a few milliseconds out of order), or the frame is
``hold_s`` older than the newest (a bus silent that long is not waited for). A
frame older than one let out already (its bus was silent past ``hold_s``, then heard) goes out at
once, late, and is counted (``late``): never dropped. The buses named when it is made (a config's)
are waited for from the first frame on, as if each had been heard then: the first frames of one
bus do not go out before the other's of the same time only because that bus was read later.
Owner: the one thread that feeds it.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable

#: One frame: time.time(), bus name, COB-ID, extended, remote, error frame, DLC, data.
Frame = tuple[float, str, int, bool, bool, bool, int, bytes]

#: How far one bus's own frames may come out of time order (stamped by two threads, handed over
#: in the other order on a busy machine: 7 ms seen on the simulator with both cores loaded).
SLACK_S = 0.1
#: How long a live view waits for a quiet bus (frame time): the longest a reader thread of a
#: busy machine hands over one bus's frames after the other's, with margin.
LIVE_HOLD_S = 2.0
#: How far a log of several buses may hold one bus's frames after the other's (a recording made
#: in arrival order on a starved machine); it costs only memory (that long of frames).
FILE_HOLD_S = 10.0


class TimeMerge:
    """Frames in (:meth:`push`) in arrival order, out in time order (see the module's docstring)."""

    def __init__(self, hold_s: float = LIVE_HOLD_S, buses: Iterable[str] = ()) -> None:
        self.hold_s = hold_s
        self._buses = tuple(buses)
        self._heap: list[tuple[float, int, Frame]] = []
        self._newest: dict[str, float] = {}  # each bus's newest frame time
        self._seq = 0  # arrival order among frames of one time
        self._out = -float("inf")  # the newest frame let out
        self.late = 0  # frames let out after a newer one

    def push(self, frame: Frame) -> list[Frame]:
        """Take ``frame``; returns the frames that may go out now, oldest first."""
        t, bus = frame[0], frame[1]
        if not self._newest:
            self._newest = dict.fromkeys(self._buses, t)
        if t > self._newest.get(bus, -float("inf")):
            self._newest[bus] = t
        heapq.heappush(self._heap, (t, self._seq, frame))
        self._seq += 1
        newest = max(self._newest.values())
        waited_for = [n for n in self._newest.values() if n >= newest - self.hold_s]
        return self._release(min(waited_for) - SLACK_S)

    def flush(self) -> list[Frame]:
        """Every frame held, oldest first (the end of the stream)."""
        return self._release(float("inf"))

    def _release(self, horizon: float) -> list[Frame]:
        out = []
        heap = self._heap
        while heap and heap[0][0] <= horizon:
            t, _, frame = heapq.heappop(heap)
            if t < self._out:
                self.late += 1
            else:
                self._out = t
            out.append(frame)
        return out

"""The broadcast manager's timer, a process of its own: it keeps the due times of the server's
cyclic jobs and, ``LEAD_S`` ahead of each, writes the job's number and due time to the server,
which schedules the job's frame on its channel with that bus time
(:meth:`virtual_can.engine.Channel.schedule`: before any frame stamped later, and at that time
at the latest), as a controller with a timed transmission queues it. Nothing else runs in this
interpreter, so no drive model, client reader or frame fan-out of the server delays a tick; a
tick that comes later than its due time (this process woke more than ``LEAD_S`` late) is on the
bus when it reached the server (the kernel's ``SO_TIMESTAMPNS`` stamp), as a client's frame is.
The emulator's stand-in for the kernel timer a real socketcand's broadcast manager uses.

Run by :class:`virtual_can.cyclic_jobs.CyclicJobs` as ``python -S -I bcm_timer.py FD`` (the
standard library only: it starts in milliseconds), ``FD`` a ``SOCK_SEQPACKET`` socket to the
server. Commands in (one per packet): ``ADD`` (job, period, first due time on
``CLOCK_MONOTONIC``, which every process of the machine shares) and ``DELETE`` (job); out: one
``TICK`` (job, due time) per due time. It ends when the server closes its end. Job numbers are
never reused: a replaced job is a delete and an add.

A tick the server's socket has no room for is dropped, never waited for: a timer blocked on a
stalled server would hold the server's commands. Each job keeps its own schedule (first due + n x
period): a late tick does not shift the next; one later than a whole period restarts the schedule
from then.

Owner: the timer process's one thread, alone; the server talks to it over a pipe.
"""

from __future__ import annotations

import heapq
import select
import socket
import struct
import sys
import time

ADD = struct.Struct("<BQdd")  # kind, job, period s, first due (CLOCK_MONOTONIC s)
DELETE = struct.Struct("<BQ")  # kind, job
TICK = struct.Struct("<Qd")  # job, due (CLOCK_MONOTONIC s)
KIND_ADD, KIND_DELETE = 1, 2
#: A tick goes out this long before its due time: a wake-up up to this late still gives the frame
#: its exact bus time (an ordinary process wakes up to a millisecond late on a busy machine).
LEAD_S = 0.002
#: Stale heap entries (deleted jobs) are dropped when they outnumber the live ones this much.
REBUILD_AT = 1024


class Timer:
    """The jobs' schedules (job -> period) and their due times in a heap of (due, job)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.periods: dict[int, float] = {}
        self.heap: list[tuple[float, int]] = []

    def command(self, packet: bytes) -> None:
        if packet[0] == KIND_ADD and len(packet) == ADD.size:
            _, job, period_s, due = ADD.unpack(packet)
            self.periods[job] = period_s
            heapq.heappush(self.heap, (due, job))
        elif packet[0] == KIND_DELETE and len(packet) == DELETE.size:
            self.periods.pop(DELETE.unpack(packet)[1], None)
            if len(self.heap) > REBUILD_AT and len(self.heap) > 2 * len(self.periods):
                self.heap = [(due, job) for due, job in self.heap if job in self.periods]
                heapq.heapify(self.heap)

    def run(self) -> None:
        while True:
            while self.heap and self.heap[0][1] not in self.periods:
                heapq.heappop(self.heap)
            timeout = self.heap[0][0] - LEAD_S - time.monotonic() if self.heap else None
            if timeout is not None and timeout <= 0:
                self.tick()  # a due tick before any command: a flood of commands does not delay it
            elif select.select([self.sock], [], [], timeout)[0]:
                packet = self.sock.recv(64)
                if not packet:
                    return  # the server closed its end
                self.command(packet)

    def tick(self) -> None:
        due, job = heapq.heappop(self.heap)
        try:
            self.sock.send(TICK.pack(job, due), socket.MSG_DONTWAIT)
        except BlockingIOError:
            pass  # the server is not reading: this tick is lost, the next is on time
        period = self.periods[job]
        late = time.monotonic() + LEAD_S - due
        heapq.heappush(self.heap, (due + period if late < period else due + late + period, job))


def main() -> None:
    sock = socket.socket(fileno=int(sys.argv[1]))
    try:
        Timer(sock).run()
    except (ConnectionError, KeyboardInterrupt):
        pass  # the server is gone: so is its timer
    finally:
        sock.close()


if __name__ == "__main__":
    main()

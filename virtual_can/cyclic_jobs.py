"""The server's broadcast-manager timer: every client's cyclic jobs ('< add >', '< update >',
'< delete >') in one heap, sent by one timer thread as a kernel's BCM would.

Owner: the timer thread (``_run``) sends; clients' reader threads add, update and delete
under the jobs' lock, which the timer never holds while it waits.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import can

from can_config.errors import ProtocolError
from can_config.realtime import make_thread_realtime
from virtual_can.engine import Channel

logger = logging.getLogger(__name__)

#: How long socket reads block before checking for shutdown.
POLL_S = 0.2
#: Periods a cyclic job ('< add >') may have.
MIN_CYCLIC_PERIOD_S = 0.0005
MAX_CYCLIC_PERIOD_S = 3600.0
#: Cyclic jobs one client may hold, and all clients together (a job is about 600 bytes).
CYCLIC_JOBS_PER_CLIENT = 65_536
CYCLIC_JOBS_TOTAL = 131_072
#: Frames per second the cyclic jobs of one client may send together, and of all clients: a
#: 1 Mbit/s bus carries about 8,000 frames a second (8 data bytes), so no one client takes more
#: than a quarter of a bus, and the timer is never asked for more than a bus carries. Within
#: them one client's jobs cannot delay another's beyond a few frames' time.
CYCLIC_RATE_PER_CLIENT = 2_000.0
CYCLIC_RATE_TOTAL = 8_000.0
#: Periods whose phase is remembered (jobs of one period share a wake-up).
PHASES_MAX = 4096
#: The cyclic timer spins to each due time for at most / at least this long (see CyclicJobs):
#: an ordinary thread wakes up to a millisecond late and yields to other threads while it spins.
SPIN_MAX_S = 0.001
SPIN_MIN_S = 0.00005
#: Under SCHED_FIFO the wake-up is on time and the spin only covers getting the interpreter
#: back, but it holds the interpreter and a core, and a client's frame that arrives during it
#: reaches the bus after the SYNC (six-drive stack runs: a 1 ms cap gave a command p99 of
#: 2.3 ms and a SYNC error p99 of 36 us; 0.2 ms gave 1.5 ms and 216-324 us).
SPIN_MAX_REALTIME_S = 0.0002
#: ... of which this last part without yielding the interpreter to other threads.
HARD_SPIN_S = 0.00015


@dataclass(eq=False)
class _CyclicJob:
    owner: object
    channel: Channel
    msg: can.Message
    period_s: float
    due: float
    entry: int = 0  # the sequence number of its live heap entry
    deleted: bool = False


class CyclicJobError(ProtocolError):
    """A cyclic job refused: over the limit of a client or of the server."""


class CyclicJobs:
    """The server's broadcast manager: frames sent on a timer of its own, one thread for every
    job of every client. Each job keeps its own schedule (start + n x period), so one late
    wake-up does not shift the ones after it; a job added with the period of another starts in
    its phase, so that one wake-up serves both. Jobs are keyed by (client, CAN id).

    The jobs wait in a heap ordered by due time, so a wake-up costs O(log n) whatever the number
    of idle jobs: 50,000 one-hour jobs of one client do not delay another's 10 ms SYNC
    (benchmarks/cyclic_jobs.py). A deleted or rescheduled job leaves its old entry behind, skipped
    when it surfaces; the heap is rebuilt when such entries outnumber the live ones. A client
    holds at most ``max_per_client`` jobs sending ``rate_per_client`` frames/s together, the
    server ``max_total`` and ``rate_total``; a job added is woken for only when it is due before
    the one the timer waits for (a flood of adds does not keep waking the timer).

    A timed wait in Python wakes 0.2-1 ms late on a loaded machine, so the thread wakes that
    much early (the longest recent lateness, doubled, at most ``SPIN_MAX_S``, or
    ``SPIN_MAX_REALTIME_S`` under SCHED_FIFO, which wakes on time) and spins to the
    due time: the emulator's stand-in for the kernel timer a real socketcand uses.

    Thread rules: every field is guarded by ``_cond``; the timer thread sends outside it.
    """

    def __init__(self, max_per_client: int = CYCLIC_JOBS_PER_CLIENT, max_total: int = CYCLIC_JOBS_TOTAL,
                 rate_per_client: float = CYCLIC_RATE_PER_CLIENT, rate_total: float = CYCLIC_RATE_TOTAL) -> None:
        self._jobs: dict[tuple[object, int], _CyclicJob] = {}
        self._by_owner: dict[object, set[int]] = {}
        self._rate: dict[object, float] = {}  # frames/s of each owner's jobs
        self._last_sent: dict[object, float] = {}  # when each owner's jobs last sent a frame (monotonic)
        self.rate_per_client = rate_per_client
        self.rate_total = rate_total
        self._heap: list[tuple[float, int, _CyclicJob]] = []
        self._seq = itertools.count()
        self._phase: dict[float, float] = {}  # period -> the due time of its first job
        self._cond = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._lateness: deque[float] = deque(maxlen=100)
        self.max_per_client = max_per_client
        self.max_total = max_total
        self.sent = 0
        self.realtime = False  # the timer thread runs under SCHED_FIFO

    def __len__(self) -> int:
        with self._cond:
            return len(self._jobs)

    def add(self, owner: object, channel: Channel, msg: can.Message, period_s: float) -> None:
        """Raises :class:`CyclicJobError` over a limit (a job replaced does not count)."""
        with self._cond:
            key = (owner, msg.arbitration_id)
            old = self._jobs.get(key)
            if old is None:
                if len(self._by_owner.get(owner, ())) >= self.max_per_client:
                    raise CyclicJobError(f"too many cyclic jobs (this client has {self.max_per_client})")
                if len(self._jobs) >= self.max_total:
                    raise CyclicJobError(f"too many cyclic jobs (the server has {self.max_total})")
            more = 1.0 / period_s - (1.0 / old.period_s if old is not None else 0.0)
            mine = self._rate.get(owner, 0.0) + more
            if mine > self.rate_per_client * (1 + 1e-9):
                raise CyclicJobError(f"this client's cyclic jobs would send {mine:.0f} frames/s, over its"
                                     f" {self.rate_per_client:.0f} (a 1 Mbit/s bus carries about 8000)")
            if sum(self._rate.values()) + more > self.rate_total * (1 + 1e-9):
                raise CyclicJobError(f"the server's cyclic jobs would send over {self.rate_total:.0f} frames/s")
            self._rate[owner] = mine
            now = time.monotonic()
            if len(self._phase) > PHASES_MAX:  # a client inventing periods: alignment is a nicety
                self._phase.clear()
            phase = self._phase.setdefault(period_s, now)  # same period: same phase
            due = phase + math.ceil(max(0.0, now - phase) / period_s) * period_s
            if old is not None:
                old.deleted = True
            job = _CyclicJob(owner, channel, msg, period_s, due)
            self._jobs[key] = job
            self._by_owner.setdefault(owner, set()).add(msg.arbitration_id)
            self._push(job)
            if self._thread is None and not self._stop:
                self._thread = threading.Thread(target=self._run, daemon=True, name="socketcand-bcm")
                self._thread.start()
            if self._heap[0][2] is job:  # due before what the timer waits for: wake it (else let it sleep)
                self._cond.notify()

    def _push(self, job: _CyclicJob) -> None:
        job.entry = next(self._seq)
        heapq.heappush(self._heap, (job.due, job.entry, job))
        if len(self._heap) > 1024 and len(self._heap) > 2 * len(self._jobs):  # mostly stale entries: rebuild
            self._heap = [e for e in self._heap if self._live(e)]
            heapq.heapify(self._heap)

    @staticmethod
    def _live(entry: tuple[float, int, _CyclicJob]) -> bool:
        return not entry[2].deleted and entry[2].entry == entry[1]

    def update(self, owner: object, msg: can.Message) -> bool:
        with self._cond:
            job = self._jobs.get((owner, msg.arbitration_id))
            if job is not None:
                job.msg = msg
            return job is not None

    def delete(self, owner: object, can_id: int) -> bool:
        with self._cond:
            job = self._jobs.pop((owner, can_id), None)
            if job is None:
                return False
            job.deleted = True
            self._rate[owner] = max(0.0, self._rate.get(owner, 0.0) - 1.0 / job.period_s)
            self._by_owner[owner].discard(can_id)
            if not self._by_owner[owner]:
                del self._by_owner[owner]
            return True

    def owns(self, owner: object) -> bool:
        with self._cond:
            return owner in self._by_owner

    def last_sent(self, owner: object) -> float:
        """When ``owner``'s jobs last sent a frame (time.monotonic()), -inf never."""
        with self._cond:
            return self._last_sent.get(owner, -math.inf)

    def drop(self, owner: object) -> None:
        with self._cond:
            for can_id in self._by_owner.pop(owner, set()):
                self._jobs.pop((owner, can_id)).deleted = True
            self._rate.pop(owner, None)
            self._last_sent.pop(owner, None)
            if not self._jobs:
                self._heap.clear()

    def _spin_s(self) -> float:
        cap = SPIN_MAX_REALTIME_S if self.realtime else SPIN_MAX_S
        return min(cap, max(SPIN_MIN_S, 2.0 * max(self._lateness, default=cap)))

    def _run(self) -> None:
        realtime = make_thread_realtime("socketcand broadcast manager timer")
        self.realtime = realtime
        while True:
            with self._cond:
                while self._heap and not self._live(self._heap[0]):
                    heapq.heappop(self._heap)
                if self._stop or not self._heap:
                    self._thread = None  # the thread lives while there are jobs; add() starts another
                    return
                due, entry, job = self._heap[0]
                wait = due - self._spin_s() - time.monotonic()
                if wait > 0:
                    timed = wait < POLL_S
                    wake_at = time.monotonic() + wait
                    if not self._cond.wait(min(wait, POLL_S)) and timed:  # timed out: how late?
                        self._lateness.append(max(0.0, time.monotonic() - wake_at))
                    continue
            while not realtime and time.monotonic() < due - HARD_SPIN_S:  # the last stretch: spin (no
                time.sleep(0)  # lock), letting other threads run (a real-time thread would lose the
                # interpreter to them and wait for it: it spins on), ...
            while time.monotonic() < due:  # ... but for the very last of it
                pass
            now = time.monotonic()
            with self._cond:
                if job.deleted or job.entry != entry:
                    continue  # deleted or replaced meanwhile
                job.due = due + job.period_s if now - due < job.period_s else now + job.period_s
                self._push(job)  # its old entry is stale now, popped when it surfaces
                self._last_sent[job.owner] = now
                msg, channel = job.msg, job.channel
            frame = can.Message(arbitration_id=msg.arbitration_id, data=msg.data, dlc=msg.dlc,
                                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame)
            try:
                channel.send(frame)
                self.sent += 1
            except can.CanError as err:
                logger.debug("cyclic frame 0x%X not sent: %s", msg.arbitration_id, err)

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._jobs.clear()
            self._by_owner.clear()
            self._rate.clear()
            self._last_sent.clear()
            self._heap.clear()
            self._cond.notify()
            thread = self._thread
        if thread is not None:
            thread.join(timeout=2.0)

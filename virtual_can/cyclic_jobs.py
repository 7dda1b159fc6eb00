"""The server's broadcast manager: every client's cyclic jobs ('< add >', '< update >',
'< delete >'), their frames sent at the ticks of a timer process of their own, as a kernel's
BCM would send them.

Owner: the jobs' table is guarded by one lock; clients' reader threads add, update and delete,
and tell the timer process (:mod:`virtual_can.bcm_timer`) the schedules; the tick reader thread
puts a ticked job's frame on its channel, stamped with the tick's kernel arrival time.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import can

from can_config.errors import ProtocolError
from can_config.realtime import SIM_PRIORITY, make_thread_realtime
from virtual_can.bcm_timer import ADD, DELETE, KIND_ADD, KIND_DELETE, TICK
from virtual_can.engine import Channel
from virtual_can.wire import ARRIVAL_ANCILLARY_BYTES, arrival_time, stamp_arrivals

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
#: The timer process's script (run by path with the standard library only: it starts in milliseconds).
TIMER_SCRIPT = Path(__file__).with_name("bcm_timer.py")
#: How long close() waits for the timer process to end after its socket closed, before killing it.
TIMER_EXIT_S = 2.0


@dataclass(eq=False)
class _CyclicJob:
    owner: object
    channel: Channel
    msg: can.Message
    period_s: float
    number: int  # the timer process's name for it (never reused)


class CyclicJobError(ProtocolError):
    """A cyclic job refused: over the limit of a client or of the server."""


class CyclicJobs:
    """The server's broadcast manager: frames sent on a timer of their own, one process for
    every job of every client. The schedules are the timer process's (:mod:`virtual_can.bcm_timer`:
    a heap of due times, each job on its own start + n x period, so 50,000 one-hour jobs of one
    client do not delay another's 10 ms SYNC, benchmarks/cyclic_jobs.py); the frames, their
    owners and the limits are this object's. A job added with the period of another starts in its
    phase, so that one wake-up serves both. Jobs are keyed by (client, CAN id); an update changes
    the frame only, here. A client holds at most ``max_per_client`` jobs sending
    ``rate_per_client`` frames/s together, the server ``max_total`` and ``rate_total``.

    Why a process: a thread of the server shares its interpreter with the client readers, the
    frame fan-out and (in one process) the drive models, and a SYNC waited for them: its period
    error at a listener grew with the number of drives (557 us p99 with six). The timer process
    has nothing else to run; it is put under SCHED_FIFO where the OS allows it
    (:mod:`can_config.realtime`, ``realtime``). Its ticks come ``LEAD_S`` ahead of their due
    time, and the tick reader schedules each frame on its channel with that bus time
    (:meth:`~virtual_can.engine.Channel.schedule`): it goes on the bus before any frame stamped
    later, and when its time comes at the latest. It starts with the first job, is started again
    (with every job) if it dies, and ends with the last job, with :meth:`close`, or with this
    process (it ends when its socket closes).

    Thread rules: every field is guarded by ``_lock``; the tick reader sends frames outside it.
    """

    def __init__(self, max_per_client: int = CYCLIC_JOBS_PER_CLIENT, max_total: int = CYCLIC_JOBS_TOTAL,
                 rate_per_client: float = CYCLIC_RATE_PER_CLIENT, rate_total: float = CYCLIC_RATE_TOTAL) -> None:
        self._jobs: dict[tuple[object, int], _CyclicJob] = {}
        self._numbered: dict[int, _CyclicJob] = {}
        self._by_owner: dict[object, set[int]] = {}
        self._rate: dict[object, float] = {}  # frames/s of each owner's jobs
        self._last_sent: dict[object, float] = {}  # when each owner's jobs last sent a frame (monotonic)
        self.rate_per_client = rate_per_client
        self.rate_total = rate_total
        self._numbers = itertools.count(1)
        self._phase: dict[float, float] = {}  # period -> the due time of its first job
        self._lock = threading.Lock()
        self._closed = False
        self._timer: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None  # the server's end of the timer's socket
        self._reader: threading.Thread | None = None
        self.max_per_client = max_per_client
        self.max_total = max_total
        self.sent = 0
        self.restarts = 0  # timer processes started again after one died
        self.realtime = False  # the timer process runs under SCHED_FIFO

    def __len__(self) -> int:
        with self._lock:
            return len(self._jobs)

    @property
    def timer_pid(self) -> int | None:
        timer = self._timer
        return timer.pid if timer is not None else None

    def add(self, owner: object, channel: Channel, msg: can.Message, period_s: float) -> None:
        """Raises :class:`CyclicJobError` over a limit (a job replaced does not count)."""
        with self._lock:
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
            if old is not None:
                self._forget(old)
            job = _CyclicJob(owner, channel, msg, period_s, next(self._numbers))
            self._jobs[key] = job
            self._numbered[job.number] = job
            self._by_owner.setdefault(owner, set()).add(msg.arbitration_id)
            if self._timer is None:
                self._start_timer()  # it is told every job, this one too
            else:
                self._schedule(job)

    def _due(self, period_s: float) -> float:
        """The first due time of a job of this period: in the phase of the first job that had it."""
        now = time.monotonic()
        if len(self._phase) > PHASES_MAX:  # a client inventing periods: alignment is a nicety
            self._phase.clear()
        phase = self._phase.setdefault(period_s, now)  # same period: same phase
        return phase + math.ceil(max(0.0, now - phase) / period_s) * period_s

    def _tell(self, packet: bytes) -> None:
        """Under the lock: a command to the timer process (a dead one is started again by the tick reader)."""
        if self._sock is not None:
            try:
                self._sock.send(packet)
            except OSError as err:
                logger.debug("broadcast manager timer not told: %s", err)

    def _schedule(self, job: _CyclicJob) -> None:
        self._tell(ADD.pack(KIND_ADD, job.number, job.period_s, self._due(job.period_s)))

    def _forget(self, job: _CyclicJob) -> None:
        """Under the lock: the job out of the table, and out of the timer's schedule."""
        self._numbered.pop(job.number, None)
        self._tell(DELETE.pack(KIND_DELETE, job.number))

    def _start_timer(self) -> None:
        """Under the lock: the timer process, told every job there is."""
        if self._closed:
            return
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        stamp_arrivals(mine)
        with theirs:
            timer = subprocess.Popen([sys.executable, "-S", "-I", str(TIMER_SCRIPT), str(theirs.fileno())],
                                     pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
        self._timer, self._sock = timer, mine
        self.realtime = make_thread_realtime("socketcand broadcast manager timer process", SIM_PRIORITY,
                                             pid=timer.pid)
        for job in self._numbered.values():
            self._schedule(job)
        self._reader = threading.Thread(target=self._read_ticks, args=(mine, timer), daemon=True,
                                        name="socketcand-bcm")
        self._reader.start()

    def _read_ticks(self, sock: socket.socket, timer: subprocess.Popen[bytes]) -> None:
        """The tick reader: each tick's frame scheduled on its channel with its bus time (the due
        time, or the tick's arrival if that is later), and delivered when that time comes."""
        flushes: list[tuple[float, int, Channel]] = []  # (bus time, seq, channel)
        order = itertools.count()
        while True:
            now = time.time()
            while flushes and flushes[0][0] <= now:
                heapq.heappop(flushes)[2].flush_scheduled(now)
            try:
                if not select.select([sock], [], [], max(0.0, flushes[0][0] - now) if flushes else None)[0]:
                    continue
                packet, ancillary, _, _ = sock.recvmsg(TICK.size, ARRIVAL_ANCILLARY_BYTES)
            except (OSError, ValueError):
                packet = b""
            if len(packet) != TICK.size:
                break
            number, due = TICK.unpack(packet)
            bus_time = max(due + time.time() - time.monotonic(), arrival_time(ancillary))
            with self._lock:
                job = self._numbered.get(number)
                if job is None:
                    continue  # deleted or replaced meanwhile
                self._last_sent[job.owner] = time.monotonic()
                msg, channel, period_s = job.msg, job.channel, job.period_s
            if bus_time < time.time() - period_s:
                continue  # read more than a period late (this server was stalled): a bus never carries the backlog
            frame = can.Message(arbitration_id=msg.arbitration_id, data=msg.data, dlc=msg.dlc, timestamp=bus_time,
                                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame)
            try:
                channel.schedule(frame)
                heapq.heappush(flushes, (bus_time, next(order), channel))
                self.sent += 1
            except can.CanError as err:
                logger.debug("cyclic frame 0x%X not sent: %s", msg.arbitration_id, err)
        self._timer_ended(sock, timer)

    def _timer_ended(self, sock: socket.socket, timer: subprocess.Popen[bytes]) -> None:
        """The tick reader, its timer's socket at its end: a timer still this object's died; it is
        reaped and another started, told every job."""
        with self._lock:
            if self._closed or self._timer is not timer:
                return
            self._detach_timer()
        self._end_timer(timer, sock, None)
        logger.error("the broadcast manager's timer process ended (exit status %s); starting it again",
                     timer.returncode)
        with self._lock:
            if not self._closed and self._timer is None and self._jobs:
                self._start_timer()
                self.restarts += 1  # after the start: whoever sees the count sees the new timer

    def update(self, owner: object, msg: can.Message) -> bool:
        with self._lock:
            job = self._jobs.get((owner, msg.arbitration_id))
            if job is not None:
                job.msg = msg
            return job is not None

    def delete(self, owner: object, can_id: int) -> bool:
        with self._lock:
            job = self._jobs.pop((owner, can_id), None)
            if job is None:
                return False
            self._forget(job)
            self._rate[owner] = max(0.0, self._rate.get(owner, 0.0) - 1.0 / job.period_s)
            self._by_owner[owner].discard(can_id)
            if not self._by_owner[owner]:
                del self._by_owner[owner]
        self._idle()
        return True

    def owns(self, owner: object) -> bool:
        with self._lock:
            return owner in self._by_owner

    def last_sent(self, owner: object) -> float:
        """When ``owner``'s jobs last sent a frame (time.monotonic()), -inf never."""
        with self._lock:
            return self._last_sent.get(owner, -math.inf)

    def drop(self, owner: object) -> None:
        with self._lock:
            for can_id in self._by_owner.pop(owner, set()):
                self._forget(self._jobs.pop((owner, can_id)))
            self._rate.pop(owner, None)
            self._last_sent.pop(owner, None)
        self._idle()

    def _detach_timer(self) -> tuple[subprocess.Popen[bytes] | None, socket.socket | None, threading.Thread | None]:
        """Under the lock: the timer, its socket and its tick reader, no longer this object's."""
        timer, sock, reader = self._timer, self._sock, self._reader
        self._timer = self._sock = self._reader = None
        return timer, sock, reader

    @staticmethod
    def _end_timer(timer: subprocess.Popen[bytes] | None, sock: socket.socket | None,
                   reader: threading.Thread | None) -> None:
        """Outside the lock: the timer process and its tick reader end (the socket closes)."""
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)  # the timer reads the end of its commands, the reader its ticks'
            except OSError:
                pass  # closed by the tick reader (a timer that died, being started again)
            sock.close()
        if timer is not None:
            try:
                timer.wait(TIMER_EXIT_S)
            except subprocess.TimeoutExpired:
                timer.kill()
                timer.wait()
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=2.0)

    def _idle(self) -> None:
        """After a delete or drop: no job left, no timer (the next add starts one)."""
        with self._lock:
            parts = self._detach_timer() if not self._jobs else (None, None, None)
        self._end_timer(*parts)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._jobs.clear()
            self._numbered.clear()
            self._by_owner.clear()
            self._rate.clear()
            self._last_sent.clear()
            parts = self._detach_timer()
        self._end_timer(*parts)

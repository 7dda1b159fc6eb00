"""A socketcand-protocol server on a :class:`~virtual_can.engine.BusEngine`.

python-can's ``socketcand`` interface is its client: ``can.Bus(interface="socketcand",
channel="can0", host="127.0.0.1", port=29536)``. Raw mode of the socketcand protocol::

    server: < hi >                     (on connect)
    client: < open can0 >      server: < ok >
    client: < rawmode >        server: < ok >
    server: < frame 123 1700000000.000123 11223344 >   (every frame on the channel)
    client: < send 123 4 11 22 33 44 >                  (put a frame on the channel)
    client: < echo >           server: < echo >

and the broadcast manager's cyclic jobs (BCM mode, also accepted in raw mode), which a kernel
timer runs on a real socketcand; here one timer thread of the server does::

    client: < add SEC USEC ID LEN B0 .. >   (send this frame every SEC.USEC seconds)
    client: < update ID LEN B0 .. >         (new data for the job, same period)
    client: < delete ID >                   (stop it)

A client's jobs end with its connection: a master that dies stops its SYNC.

Every reply is a separate write (python-can reads the handshake replies one ``recv`` each and
compares them exactly). Separate writes still coalesce in the client's socket when frames follow
at once, so after the ``rawmode`` reply a client's frames are held until it sends its first line
or ``RAWMODE_HOLD_S`` passes: held frames are delivered late, never dropped.
Each client has a reader and a writer thread and a bounded outgoing queue: a client that
stops reading loses frames and is then dropped, a malformed line gets ``< error ... >``, and
neither affects any other client. The server binds loopback unless told otherwise.
"""

from __future__ import annotations

import ctypes
import heapq
import itertools
import logging
import math
import select
import socket
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import can

from can_config.errors import ProtocolError, SimError
from can_config.realtime import make_thread_realtime
from virtual_can.engine import BusEngine, Channel, Endpoint

logger = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 29536
#: Longest protocol line accepted; a longer one is an error and is discarded.
MAX_LINE_CHARS = 256
#: Bytes of frames queued for a client that is not reading before frames are dropped (about
#: 20,000 frames); the memory is one buffer per client, released when the client goes.
CLIENT_QUEUE_BYTES = 1 << 20
#: Replies waiting for a client that does not read them before it is disconnected.
CLIENT_REPLIES_MAX = 1_000
#: Frames dropped in a row for one client before that client is disconnected.
SLOW_CLIENT_DROP_LIMIT = 20_000
#: Protocol errors from one client before it is disconnected.
CLIENT_ERROR_LIMIT = 100
DEFAULT_MAX_CLIENTS = 64
#: After the rawmode '< ok >', frames wait this long (or until the client speaks) so that the
#: reply reaches the client's handshake read on its own.
RAWMODE_HOLD_S = 0.05
#: A client that has not reached rawmode (nor added a cyclic job) this long after connecting is
#: closed (idle connections would otherwise hold every client slot).
HANDSHAKE_TIMEOUT_S = 5.0
#: With every slot taken, a new client gets the slot of the client silent longest, when that
#: one has sent nothing (no frame, no command, no echo) for this long: longer than any idle of
#: python-can's socketcand bus or of the driver's cyclic job, which says ``< echo >`` every 10 s.
IDLE_TIMEOUT_S = 60.0
#: Periods a cyclic job ('< add >') may have.
MIN_CYCLIC_PERIOD_S = 0.0005
MAX_CYCLIC_PERIOD_S = 3600.0
#: Cyclic jobs one client may hold, and all clients together (a job is about 600 bytes).
CYCLIC_JOBS_PER_CLIENT = 65_536
CYCLIC_JOBS_TOTAL = 131_072
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
#: How long socket reads block before checking for shutdown.
POLL_S = 0.2
_LOOPBACK = ("127.0.0.1", "localhost", "::1")
#: Linux's SO_TIMESTAMPNS (the socket module does not name it): each read carries the time its
#: data reached the socket, which is when the client's frame reached the bus. A frame is stamped
#: with it, as a CAN controller stamps a frame on the wire, not with the moment this server's
#: interpreter got round to it (its drive threads can hold it for a tick).
_SO_TIMESTAMPNS: int | None = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform == "linux" else None)
_TIMESPEC = struct.Struct("@ll")
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)


def _stamp_arrivals(sock: socket.socket) -> None:
    """Ask the kernel to stamp every read of ``sock`` (where it can; else frames are stamped
    when read)."""
    if _SO_TIMESTAMPNS is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            pass


def _arrival(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's arrival time of a read, or now where it gave none."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return float(sec + nsec * 1e-9)
    return time.time()


def _load_malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim  # type: ignore[no-any-return]
    except (OSError, AttributeError):
        return None  # not glibc: the allocator keeps what it keeps


_MALLOC_TRIM = _load_malloc_trim()


def _return_free_memory() -> None:
    """After a client is gone: hand the heap's free pages back to the system (glibc keeps them
    otherwise, and a server that outlived 40 flooded clients stayed 100 MB larger)."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def format_frame(msg: can.Message) -> str:
    """``< frame ID SEC.USEC HEXDATA >`` with a 3-digit standard or 8-digit extended id (a
    remote frame has no data: rawmode has no RTR marker)."""
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = b"" if msg.is_remote_frame else bytes(msg.data)
    return f"< frame {can_id} {msg.timestamp:.6f} {data.hex().upper()} >"


_HEX = frozenset("0123456789abcdefABCDEF")


def _hex(word: str, max_digits: int, what: str, line: str) -> int:
    """A field of hex digits only (no sign, prefix or underscore), at most ``max_digits``."""
    if not 1 <= len(word) <= max_digits or not _HEX.issuperset(word):
        raise ProtocolError(f"{what} {word[:12]!r} in {line[:60]!r}: expected 1 to {max_digits} hex digits")
    return int(word, 16)


def parse_send(line: str) -> can.Message:
    """Parse ``< send ID LEN B0 B1 ... >`` into a message. Raises :class:`ProtocolError`.

    Strict: every field is hex digits only. The id is extended when written with 8 digits (the
    form socketcand and python-can write) or when its value exceeds 0x7FF; otherwise standard.
    LEN > 0 with no data bytes is a remote frame (RTR) of that DLC: python-can sends those so."""
    parts = line[1:-1].split()
    if len(parts) < 3 or parts[0] != "send":
        raise ProtocolError(f"expected '< send ID LEN B0 .. >', got {line[:60]!r}")
    can_id = _hex(parts[1], 8, "CAN id", line)
    length = _hex(parts[2], 1, "length", line)
    data = bytes(_hex(b, 2, "data byte", line) for b in parts[3:])
    extended = len(parts[1]) == 8 or can_id > 0x7FF
    if can_id > 0x1FFFFFFF:
        raise ProtocolError(f"CAN id {parts[1]} out of range (0..7FF standard, 0..1FFFFFFF extended)")
    if length > 8:
        raise ProtocolError(f"length {length} out of range (0..8)")
    if not data and length:
        return can.Message(arbitration_id=can_id, dlc=length, is_remote_frame=True, is_extended_id=extended,
                           timestamp=0.0)
    if len(data) != length:
        raise ProtocolError(f"length {length} does not match {len(data)} data bytes")
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended, timestamp=0.0)


def parse_add(line: str) -> tuple[float, can.Message]:
    """Parse ``< add SEC USEC ID LEN B0 .. >`` into (period in s, message). Raises
    :class:`ProtocolError`; the period must be at least ``MIN_CYCLIC_PERIOD_S``."""
    parts = line[1:-1].split()
    if len(parts) < 5 or parts[0] != "add" or not all(p.isdigit() for p in parts[1:3]):
        raise ProtocolError(f"expected '< add SEC USEC ID LEN B0 .. >', got {line[:60]!r}")
    period = int(parts[1]) + int(parts[2]) / 1e6
    if not MIN_CYCLIC_PERIOD_S <= period <= MAX_CYCLIC_PERIOD_S:
        raise ProtocolError(f"cyclic period {period:g} s out of range ({MIN_CYCLIC_PERIOD_S:g} to"
                            f" {MAX_CYCLIC_PERIOD_S:g} s)")
    return period, parse_send("< send " + " ".join(parts[3:]) + " >")


@dataclass(eq=False)
class _CyclicJob:
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
    holds at most ``max_per_client`` jobs, the server ``max_total``.

    A timed wait in Python wakes 0.2-1 ms late on a loaded machine, so the thread wakes that
    much early (the longest recent lateness, doubled, at most ``SPIN_MAX_S``, or
    ``SPIN_MAX_REALTIME_S`` under SCHED_FIFO, which wakes on time) and spins to the
    due time: the emulator's stand-in for the kernel timer a real socketcand uses.

    Thread rules: every field is guarded by ``_cond``; the timer thread sends outside it.
    """

    def __init__(self, max_per_client: int = CYCLIC_JOBS_PER_CLIENT, max_total: int = CYCLIC_JOBS_TOTAL) -> None:
        self._jobs: dict[tuple[object, int], _CyclicJob] = {}
        self._by_owner: dict[object, set[int]] = {}
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
            if key not in self._jobs:
                if len(self._by_owner.get(owner, ())) >= self.max_per_client:
                    raise CyclicJobError(f"too many cyclic jobs (this client has {self.max_per_client})")
                if len(self._jobs) >= self.max_total:
                    raise CyclicJobError(f"too many cyclic jobs (the server has {self.max_total})")
            now = time.monotonic()
            if len(self._phase) > PHASES_MAX:  # a client inventing periods: alignment is a nicety
                self._phase.clear()
            phase = self._phase.setdefault(period_s, now)  # same period: same phase
            due = phase + math.ceil(max(0.0, now - phase) / period_s) * period_s
            old = self._jobs.get(key)
            if old is not None:
                old.deleted = True
            job = _CyclicJob(channel, msg, period_s, due)
            self._jobs[key] = job
            self._by_owner.setdefault(owner, set()).add(msg.arbitration_id)
            self._push(job)
            if self._thread is None and not self._stop:
                self._thread = threading.Thread(target=self._run, daemon=True, name="socketcand-bcm")
                self._thread.start()
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
            self._by_owner[owner].discard(can_id)
            if not self._by_owner[owner]:
                del self._by_owner[owner]
            return True

    def owns(self, owner: object) -> bool:
        with self._cond:
            return owner in self._by_owner

    def drop(self, owner: object) -> None:
        with self._cond:
            for can_id in self._by_owner.pop(owner, set()):
                self._jobs.pop((owner, can_id)).deleted = True
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
            self._heap.clear()
            self._cond.notify()
            thread = self._thread
        if thread is not None:
            thread.join(timeout=2.0)


@dataclass
class ClientStats:
    received: int = 0
    sent: int = 0
    dropped: int = 0
    errors: int = 0


class _Client:
    def __init__(self, server: SocketcandServer, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.server = server
        self.sock = sock
        self.addr = addr
        self.stats = ClientStats()
        self.channel: Channel | None = None
        self.endpoint: Endpoint | None = None
        self.raw = False
        # what waits to be written, in order: runs of frames (one bytearray each, bounded in bytes
        # together) and replies (bytes, each its own write). Guarded by _out_cond.
        self._out: deque[bytearray | bytes] = deque()
        self._out_frame_bytes = 0
        self._out_cond = threading.Condition()
        self._drops_in_row = 0
        self._closed = threading.Event()
        self._hold_frames = False  # set by rawmode: frames wait for _spoke or RAWMODE_HOLD_S
        self._spoke = threading.Event()
        self._arrival = 0.0  # when the newest read reached the socket; the reader's own
        self.last_heard = time.monotonic()  # written by the reader, read by the accept loop
        _stamp_arrivals(sock)
        name = f"{addr[0]}:{addr[1]}"
        self.reader = threading.Thread(target=self._read_loop, daemon=True, name=f"socketcand-rx-{name}")
        self.writer = threading.Thread(target=self._write_loop, daemon=True, name=f"socketcand-tx-{name}")

    def start(self) -> None:
        self._reply("< hi >")
        self.reader.start()
        self.writer.start()

    # engine -> client
    def _on_frame(self, msg: can.Message) -> None:
        if not self.raw:
            return
        line = format_frame(msg).encode("ascii")
        with self._out_cond:
            if self._out_frame_bytes + len(line) <= CLIENT_QUEUE_BYTES:
                if self._out and isinstance(self._out[-1], bytearray):
                    self._out[-1] += line  # the run of frames the writer has not taken yet
                else:
                    self._out.append(bytearray(line))
                self._out_frame_bytes += len(line)
                self._drops_in_row = 0
                self._out_cond.notify()
                return
        self.stats.dropped += 1
        self._drops_in_row += 1
        if self._drops_in_row == SLOW_CLIENT_DROP_LIMIT:
            logger.warning("socketcand client %s stopped reading; disconnecting it", self.addr)
            threading.Thread(target=self.close, daemon=True, name="socketcand-drop").start()

    def _reply(self, line: str) -> None:
        """Protocol replies go out as their own write, in order with frames; what they quote of
        the client's input is escaped to ASCII."""
        with self._out_cond:
            if len(self._out) > CLIENT_REPLIES_MAX:
                self._out_cond.notify()
                threading.Thread(target=self.close, daemon=True, name="socketcand-drop").start()
                return
            self._out.append(line.encode("ascii", "backslashreplace"))
            self._out_cond.notify()

    def _write_loop(self) -> None:
        sock = self.sock
        while not self._closed.is_set():
            with self._out_cond:
                if not self._out:
                    self._out_cond.wait(POLL_S)
                    continue
                chunk = self._out.popleft()
                if isinstance(chunk, bytearray):
                    self._out_frame_bytes -= len(chunk)
            if isinstance(chunk, bytearray):
                if self._hold_frames:
                    self._spoke.wait(RAWMODE_HOLD_S)
                    self._hold_frames = False
                self.stats.sent += chunk.count(b"<")
            try:
                sock.sendall(chunk)
            except OSError:
                break
        self.close()

    # client -> engine
    def _read_loop(self) -> None:
        buf = ""
        sock = self.sock
        connected = time.monotonic()
        # the socket stays blocking for the writer: a client that pauses reading is not dropped
        # for a short stall, only after SLOW_CLIENT_DROP_LIMIT frames lost in a row; the reader
        # waits with select so that it notices shutdown
        while not self._closed.is_set():
            try:
                readable, _, _ = select.select([sock], [], [], POLL_S)
                if not self.raw and time.monotonic() - connected > self.server.handshake_timeout_s \
                        and not self.server.cyclic.owns(self):  # a BCM-mode client with a cyclic job stays
                    logger.info("socketcand client %s: no rawmode (nor a cyclic job) within %g s; closing it",
                                self.addr, self.server.handshake_timeout_s)
                    break
                if not readable:
                    continue
                chunk, ancillary, _, _ = sock.recvmsg(65536, _ANCILLARY_BYTES)
                self._arrival = _arrival(ancillary)
                self.last_heard = time.monotonic()
            except (OSError, ValueError):
                break
            if not chunk:
                break
            buf += chunk.decode("ascii", errors="backslashreplace")  # what is quoted back stays ASCII
            while True:
                start = buf.find("<")
                if start < 0:
                    if buf.strip():
                        self._error("data outside '< ... >'")
                    buf = ""
                    break
                end = buf.find(">", start)
                if end < 0:
                    if len(buf) - start > MAX_LINE_CHARS:
                        self._error(f"line longer than {MAX_LINE_CHARS} characters")
                        buf = ""
                    else:
                        buf = buf[start:]
                    break
                line = buf[start:end + 1]
                if self.raw:
                    self._spoke.set()
                if buf[:start].strip():
                    self._error("data outside '< ... >'")
                buf = buf[end + 1:]
                self._handle(line)
            if self.stats.errors >= CLIENT_ERROR_LIMIT:
                logger.warning("socketcand client %s sent %d bad lines; disconnecting it",
                               self.addr, self.stats.errors)
                break
        self.close()

    def _error(self, what: str) -> None:
        self.stats.errors += 1
        self._reply(f"< error {what} >")

    def _handle(self, line: str) -> None:
        words = line[1:-1].split()
        if not words:
            self._error("empty command")
            return
        cmd = words[0]
        if cmd == "send" and self.channel is not None:
            try:
                msg = parse_send(line)
            except ProtocolError as err:
                self._error(str(err))
                return
            self.stats.received += 1
            msg.timestamp = self._arrival
            try:
                self.channel.send(msg, self.endpoint)
            except can.CanError as err:
                self._error(str(err))
        elif cmd == "open" and len(words) == 2 and self.channel is None:
            if not self.server.channel_allowed(words[1]):
                self._error(f"no such channel {words[1]}; served: {', '.join(self.server.channels)}")
                return
            self.channel = self.server.engine.channel(words[1])
            self._reply("< ok >")
        elif cmd == "rawmode" and self.channel is not None:
            self._hold_frames = True
            self._reply("< ok >")
            self.raw = True
            if self.endpoint is None:
                self.endpoint = self.channel.attach(self._on_frame, name=f"client:{self.addr}")
        elif cmd == "echo":
            self._reply("< echo >")
        elif cmd in ("add", "update", "delete") and self.channel is not None:
            self._cyclic(cmd, words, line)
        else:
            self._error("unknown command")

    def _cyclic(self, cmd: str, words: list[str], line: str) -> None:
        jobs = self.server.cyclic
        assert self.channel is not None
        try:
            if cmd == "add":
                period, msg = parse_add(line)
                jobs.add(self, self.channel, msg, period)
            elif cmd == "update":
                if not jobs.update(self, parse_send("< send " + " ".join(words[1:]) + " >")):
                    self._error(f"no cyclic job with id {words[1]}")
            elif len(words) != 2 or not jobs.delete(self, _hex(words[1], 8, "CAN id", line)):
                self._error(f"no cyclic job with id {' '.join(words[1:])}")
        except ProtocolError as err:
            self._error(str(err))

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self.server.cyclic.drop(self)  # its cyclic jobs end with it
        if self.endpoint is not None:
            self.endpoint.detach()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        with self._out_cond:
            self._out.clear()  # the queued frames' memory goes with the client
            self._out_frame_bytes = 0
        self.server._forget(self)
        _return_free_memory()

    def join(self, timeout: float) -> None:
        for thread in (self.reader, self.writer):
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join(timeout)

    @property
    def closed(self) -> bool:
        return self._closed.is_set()


class SocketcandServer:
    """Serves the channels of a :class:`BusEngine` over TCP. Context manager; ``close()`` is idempotent."""

    def __init__(self, engine: BusEngine, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *,
                 channels: tuple[str, ...] = ("can0",), allow_any_channel: bool = False,
                 max_clients: int = DEFAULT_MAX_CLIENTS, allow_remote: bool = False,
                 handshake_timeout_s: float = HANDSHAKE_TIMEOUT_S, idle_timeout_s: float = IDLE_TIMEOUT_S) -> None:
        if host not in _LOOPBACK and not host.startswith("127."):
            if not allow_remote:
                raise SimError(f"refusing to bind {host!r}: the bus server listens on loopback"
                               " (127.0.0.1) unless allow_remote=True (CLI: --allow-remote)")
            logger.warning("bus server binding %s: every host that reaches it can drive the motors",
                           host)
        self.engine = engine
        self.channels = channels
        self.allow_any_channel = allow_any_channel
        self.max_clients = max_clients
        self.handshake_timeout_s = handshake_timeout_s
        self.idle_timeout_s = idle_timeout_s
        self.idle_closed = 0
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()
        self.cyclic = CyclicJobs()
        self._sock = socket.create_server((host, port), reuse_port=False)
        self._sock.settimeout(POLL_S)
        self.host, self.port = self._sock.getsockname()[:2]
        self._stop = threading.Event()
        for name in channels:
            engine.channel(name)
        self._thread = threading.Thread(target=self._accept_loop, daemon=True,
                                        name=f"socketcand-accept-{self.port}")
        self._thread.start()
        logger.info("socketcand server on %s:%d serving %s", self.host, self.port, ", ".join(channels))

    def channel_allowed(self, name: str) -> bool:
        return self.allow_any_channel or name in self.channels

    @property
    def clients(self) -> list[_Client]:
        with self._lock:
            return list(self._clients)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, addr = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            try:
                self._admit(sock, addr)
            except OSError as err:  # one connection's failure (reset at once, ...) never ends the loop
                logger.info("client %s: dropped while connecting (%s)", addr, err)
                sock.close()

    def _admit(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            full = len(self._clients) >= self.max_clients
        if full and self._free_an_idle_slot(addr):
            full = False
        if full:
            logger.warning("refusing client %s: %d clients already", addr, self.max_clients)
            try:
                sock.sendall(b"< error too many clients >")
            finally:
                sock.close()
            return
        client = _Client(self, sock, addr)
        with self._lock:
            self._clients.add(client)
        client.start()

    def _free_an_idle_slot(self, newcomer: tuple[str, int]) -> bool:
        """Slots full: close the client silent longest, if silent for ``idle_timeout_s`` (in
        rawmode or BCM mode alike: a connection that only holds a slot, or a cyclic job, and
        never speaks)."""
        now = time.monotonic()
        with self._lock:
            idle = max(self._clients, key=lambda c: now - c.last_heard, default=None)
        if idle is None or now - idle.last_heard < self.idle_timeout_s:
            return False
        logger.info("slots full: closing client %s (silent for %.0f s) to admit %s", idle.addr,
                    now - idle.last_heard, newcomer)
        idle.close()
        self.idle_closed += 1
        return True

    def _forget(self, client: _Client) -> None:
        with self._lock:
            self._clients.discard(client)

    def disconnect_clients(self) -> int:
        """Fault injection: drop every client connection (a bus-off as the clients see it)."""
        clients = self.clients
        for client in clients:
            client.close()
        return len(clients)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        try:
            self._sock.close()
        finally:
            self._thread.join(timeout=2.0)
            clients = self.clients
            for client in clients:
                client.close()
            for client in clients:
                client.join(timeout=2.0)
            self.cyclic.close()

    def __enter__(self) -> SocketcandServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

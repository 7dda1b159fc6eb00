"""One socketcand client of the server: the protocol's parsing and formatting, its reader
thread (lines in) and writer thread (frames and replies out, a bounded queue).

Owner: each client's reader thread owns its protocol state (mode, errors); the writer thread
owns the socket's sends; the bus engine's thread only appends to the bounded queue.
"""

from __future__ import annotations

import ctypes
import logging
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import can

from can_config.errors import ProtocolError
from virtual_can.cyclic_jobs import MAX_CYCLIC_PERIOD_S, MIN_CYCLIC_PERIOD_S, POLL_S, CyclicJobs
from virtual_can.engine import BusEngine, Channel, Endpoint
from virtual_can.wire import ARRIVAL_ANCILLARY_BYTES, arrival_time, stamp_arrivals, tcp_bytes_received


class ClientHost(Protocol):
    """What a client needs of the server that accepted it (the server is one; the client does not
    import it): the bus, the cyclic jobs, the channels it may open, and a way to be forgotten."""

    engine: BusEngine
    cyclic: CyclicJobs
    channels: tuple[str, ...]
    handshake_timeout_s: float

    def channel_allowed(self, name: str) -> bool: ...

    def forget(self, client: Client) -> None: ...


logger = logging.getLogger(__name__)

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
#: After the rawmode '< ok >', frames wait this long (or until the client speaks) so that the
#: reply reaches the client's handshake read on its own.
RAWMODE_HOLD_S = 0.05
#: Cyclic job commands ('< add >', '< update >', '< delete >') one client may give per second, in
#: bursts of up to as many: past it the client's own reader waits, so a flood of commands (8 MB
#: of '< add >' replacing one job) slows that client, not the server's timer and other clients.
JOB_COMMANDS_PER_S = 1_000.0
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


@dataclass
class ClientStats:
    received: int = 0
    sent: int = 0
    dropped: int = 0
    errors: int = 0


class Client:
    def __init__(self, server: ClientHost, sock: socket.socket, addr: tuple[str, int]) -> None:
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
        self._handled_bytes = 0  # bytes read from the socket whose frames are on the bus (the reader's)
        self._handled_arrival = 0.0  # the kernel's arrival stamp of the newest read they came in (the reader's)
        self.last_heard = time.monotonic()  # written by the reader, read by the accept loop
        # the last frame or command other than an echo (reader), read by the accept loop: an echo
        # every few seconds keeps a connection open but is no use of the bus
        self.last_active = self.last_heard
        self._job_tokens, self._job_tokens_at = JOB_COMMANDS_PER_S, self.last_heard  # the reader's
        stamp_arrivals(sock)
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
        handshaken = False  # rawmode, or a cyclic job once: a BCM client's later < delete > does not undo it
        # the socket stays blocking for the writer: a client that pauses reading is not dropped
        # for a short stall, only after SLOW_CLIENT_DROP_LIMIT frames lost in a row; the reader
        # waits with select so that it notices shutdown
        while not self._closed.is_set():
            try:
                readable, _, _ = select.select([sock], [], [], POLL_S)
                if not self.raw and not handshaken and self.server.cyclic.owns(self):
                    handshaken = True  # a BCM-mode client with a cyclic job stays
                if not self.raw and not handshaken and time.monotonic() - connected > self.server.handshake_timeout_s:
                    logger.info("socketcand client %s: no rawmode (nor a cyclic job) within %g s; closing it",
                                self.addr, self.server.handshake_timeout_s)
                    break
                if not readable:
                    continue
                chunk, ancillary, _, _ = sock.recvmsg(65536, ARRIVAL_ANCILLARY_BYTES)
                self._arrival = arrival_time(ancillary)
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
            self._handled_arrival = self._arrival  # every whole frame of the read is on the bus now
            self._handled_bytes += len(chunk)
            if self.stats.errors >= CLIENT_ERROR_LIMIT:
                logger.warning("socketcand client %s sent %d bad lines; disconnecting it",
                               self.addr, self.stats.errors)
                break
        self.close()

    def on_bus_until(self, wall: float) -> float:
        """The bus time up to which every frame this client sent is on the bus, asked at ``wall``:
        ``wall`` when the kernel has received no byte of it that is not (the reader's count of the
        bytes it handled against the kernel's of those received), else the arrival stamp of the
        newest read the reader handled: what came after may still be in the socket, or read by a
        reader thread starved before it put it on the bus. Any thread."""
        handled, arrival = self._handled_bytes, self._handled_arrival
        received = tcp_bytes_received(self.sock)
        if received is None or received <= handled or self._closed.is_set() or not self.reader.is_alive():
            return wall  # nothing in flight, or no reader left to bring it
        return min(wall, arrival)

    def _error(self, what: str) -> None:
        self.stats.errors += 1
        self._reply(f"< error {what} >")

    def _handle(self, line: str) -> None:
        words = line[1:-1].split()
        if not words:
            self._error("empty command")
            return
        cmd = words[0]
        if cmd != "echo":  # an echo keeps the connection, but is no use of the bus
            self.last_active = time.monotonic()
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
            self._pace_job_commands()
            self._cyclic(cmd, words, line)
        else:
            self._error("unknown command")

    def _pace_job_commands(self) -> None:
        """Reader: a token per job command, JOB_COMMANDS_PER_S of them a second; none left: wait."""
        now = time.monotonic()
        self._job_tokens = min(JOB_COMMANDS_PER_S, self._job_tokens + (now - self._job_tokens_at) * JOB_COMMANDS_PER_S)
        self._job_tokens_at = now
        if self._job_tokens < 1.0:
            self._closed.wait((1.0 - self._job_tokens) / JOB_COMMANDS_PER_S)
            self._job_tokens, self._job_tokens_at = 1.0, time.monotonic()
        self._job_tokens -= 1.0

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
        self.server.forget(self)
        _return_free_memory()

    def join(self, timeout: float) -> None:
        for thread in (self.reader, self.writer):
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join(timeout)

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

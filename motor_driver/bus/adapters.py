"""The places where the driver leans on a dependency's internals, kept in one module.

Each is pinned by ``tests/test_adapters.py`` against the installed version, so an upgrade
that changes the behaviour fails there, loudly, instead of in the field:

- :func:`connection_closed`: python-can's socketcand client reads the end of its TCP stream as
  "no frame" and never raises, so a vanished server is invisible through its public API; a
  peek at its socket (a name-mangled private attribute) tells.
- :func:`hold_lone_sync`: the same socket's receive low-water mark, so that the echo of the
  driver's own SYNC, alone, does not wake the bus's receive thread.
- :func:`batch_receive`: the same client's receive, read from its socket by this driver: every
  frame of one read parsed in one pass (:func:`parse_frame_tuples`), without python-can's per-read
  debug text and its warning for each frame a read cut in two; with :func:`dispatch_batches`, the
  read's frames handed to the bus's listener in one call, no ``can.Message`` made for them.
- :func:`socketcand_sender`: the same client's send, written to its socket by this driver: the
  text python-can would write for the frame, without the ``can.Message``, the per-send debug
  text and the layers in between (every command's RPDO goes this way); with
  :meth:`GuardedNetwork.one_write`, a SYNC's set-points of several drives in one write, the
  order on the wire still the order of the sends of every thread.
- :func:`bound_sends`: the same socket's writes bounded (SO_SNDTIMEO): a server that stopped
  reading held a write, and the send lock with it, for ever; :func:`stall_of` gives the
  connection up and says why.
- :class:`GuardedNetwork`: canopen's ``Network.notify`` stops the receive thread when one
  callback raises; this override isolates each callback (its loop mirrors canopen's). Its
  listener also drops 29-bit frames, which canopen would dispatch by their low bits.
- :class:`ReceiveErrors`, :func:`quiet_dependency_tracebacks`: a lost bus is
  one line. python-can's socketcand client puts a formatted traceback in its "Failed to receive"
  error (and logs it), its broadcast manager logs a send error with its traceback, and its
  Notifier re-raises a receive error in its thread (Python prints that traceback) unless a
  listener takes it.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import select
import socket
import struct
import termios
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from typing import Any, NamedTuple

import can
import canopen

from motor_driver.process.jobs import brief_error
from motor_driver.process.ratelimit import Throttle

logger = logging.getLogger(__name__)

#: python-can's socketcand client keeps its socket here (name-mangled private attribute).
SOCKETCAND_SOCKET_ATTRIBUTE = "_SocketCanDaemonBus__socket"


def connection_closed(bus: can.BusABC) -> bool:
    """True when a TCP bus (python-can's ``socketcand`` client) has lost its server.

    python-can reads the end of the stream as 'no frame', so ``recv()`` then spins until its
    timeout and never raises; a peek at the socket tells. Other interfaces: False.
    """
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return False
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


#: The longest one write to a socketcand bus's socket may block (SO_SNDTIMEO). It blocks only
#: when the connection's buffers are full: the server has not read for about a second of traffic or
#: more (hung, stopped, blocked on its own CAN write with no node acknowledging, a dropped link).
#: Unbounded, that write held the bus's send lock for ever: every other sender (another thread's
#: stop, an SDO) waited behind it, and nothing said why. Past it the connection is given up
#: (:func:`stall_of`) and the supervisor reconnects, naming the stall.
SEND_STALL_S = 0.2
#: Why a socketcand bus's connection was given up after a write that blocked (:func:`stall_of`).
SEND_STALLED_ATTRIBUTE = "_rovercan_send_stalled"


class SendStalled(can.CanOperationError):  # type: ignore[misc]
    """A write to a socketcand server blocked SEND_STALL_S (or followed one that did): the
    connection was given up; the message says why."""


def bound_sends(bus: can.BusABC) -> can.BusABC:
    """A socketcand bus whose socket's writes block at most SEND_STALL_S (SO_SNDTIMEO; its reads
    are untouched), and whose own ``send`` (the SYNC thread's, the host heartbeat's) gives the
    connection up inside its caller's lock when one did (:func:`stall_of`): a writer waiting for
    the lock never adds to a frame cut in two. Other interfaces (python-can's SocketCAN send never
    blocks) are left as they are. Returns ``bus``."""
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return bus
    whole = int(SEND_STALL_S)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", whole, round((SEND_STALL_S - whole) * 1e6)))
    send = bus.send

    def bounded(msg: can.Message, timeout: float | None = None) -> None:
        try:
            send(msg, timeout)
        except OSError as err:
            why = stall_of(bus, err)
            if why:
                raise SendStalled(why) from err
            raise

    bus.send = bounded  # type: ignore[method-assign]  # this one bus, as batch_receive does
    return bus


def stall_of(bus: can.BusABC | None, err: BaseException | None = None) -> str:
    """Why ``bus``'s connection was given up after a write that blocked, or '' (never given up).
    ``err``, a write's error: a write that timed out (EAGAIN from :func:`bound_sends`'s bound)
    gives the connection up now: its write side shut, so that no later frame completes the text
    of one cut in two (the server reads the end of the stream instead), and the reason kept."""
    why = str(getattr(bus, SEND_STALLED_ATTRIBUTE, ""))
    if why or not isinstance(err, BlockingIOError):
        return why
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return ""
    why = (f"a write to the socketcand server blocked for {SEND_STALL_S * 1000:.0f} ms (the connection full: the"
           " server stopped reading: hung or stopped, its own CAN writes blocked with no node acknowledging,"
           " or the link dropped); the connection was given up")
    setattr(bus, SEND_STALLED_ATTRIBUTE, why)
    try:
        sock.shutdown(socket.SHUT_WR)
    except OSError:
        pass
    return why


def room_to_send(bus: can.BusABC) -> bool:
    """False when a socketcand bus's socket would block a write now (its buffer full: the server
    is not reading): the supervisor's host heartbeat is then not written, and its loop never waits
    on one bus. True for other interfaces."""
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return True
    try:
        return bool(select.select([], [sock], [], 0)[1])
    except (OSError, ValueError):  # closed: the write says so
        return True


#: How long a socketcand bus's read pauses once it found its server gone (:func:`pause_when_closed`).
CLOSED_PAUSE_S = 0.05


def pause_when_closed(bus: can.BusABC) -> can.BusABC:
    """A socketcand bus whose server has gone pauses CLOSED_PAUSE_S after each read that found
    nothing (python-can reads the end of the stream as 'no frame' at once, so its ``recv()``
    went round until its timeout): the bus's receive thread, real-time, would otherwise spin
    until the supervisor drops the bus (:func:`connection_closed`, about every 50 ms). Other
    interfaces are left as they are. Returns ``bus``."""
    if not isinstance(getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None), socket.socket):
        return bus
    inner = bus._recv_internal

    def recv_internal(timeout: float | None) -> tuple[can.Message | None, bool]:
        msg, filtered = inner(timeout)
        if msg is None and connection_closed(bus):
            time.sleep(CLOSED_PAUSE_S)
        return msg, filtered

    bus._recv_internal = recv_internal  # type: ignore[method-assign]  # this one bus, as python-can keeps it
    return bus


#: python-can's socketcand client keeps what it parsed and not yet returned, and the text not yet parsed, here
SOCKETCAND_BUFFERS = ("_SocketCanDaemonBus__message_buffer", "_SocketCanDaemonBus__receive_buffer")
SOCKETCAND_TCP_TUNE = "_SocketCanDaemonBus__tcp_tune"
#: one read of the socket takes at most this much (a SYNC period's frames of three buses fit)
RECEIVE_CHUNK_BYTES = 65536


#: A frame the batch read hands on: (id, data, the bus's stamp, flags: FRAME_EXTENDED, FRAME_ERROR as
#: the flight recorder stores them; socketcand's rawmode has no remote frames). No ``can.Message``.
Frame = tuple[int, bytearray, float, int]
FRAME_EXTENDED, FRAME_REMOTE, FRAME_ERROR = 1, 2, 4


def parse_frame_tuples(text: str) -> tuple[list[Frame], str]:
    """The frames of socketcand's rawmode text (``< frame ID SECONDS.MICROS DATA >``; ``< error
    ID SECONDS.MICROS ... >`` an error frame, as python-can reads it) in one pass, as
    :data:`Frame` tuples, and the text after the last complete one (a frame a read cut in two).
    Other messages (``< ok >``) are skipped, and so is a frame whose fields do not parse (python-can
    raised, and the whole read was lost with it: the bus taken for lost) or that no classic CAN bus
    carries (an 11-bit id above 0x7FF, a 29-bit one above 0x1FFFFFFF, data beyond 8 bytes: python-can
    passes them on, and the recorder's slot could not hold them). The same fields as
    python-can's ``convert_ascii_message_to_can_message``."""
    out: list[Frame] = []
    end = 0
    find, append = text.find, out.append
    while (start := find("<", end)) != -1:
        close = find(">", start)
        if close == -1:
            return out, text[start:] if len(text) - start <= 200 else ""  # python-can drops a longer one too
        body = text[start + 1:close].split()
        end = close + 1
        if len(body) < 3:
            continue
        try:
            if body[0] == "frame":
                ident = body[1]
                can_id, data = int(ident, 16), bytearray.fromhex(body[3]) if len(body) > 3 else bytearray()
                if can_id > (0x7FF if len(ident) == 3 else 0x1FFFFFFF) or len(data) > 8:
                    continue  # no classic CAN frame (an id beyond its width, more than 8 bytes): skipped
                append((can_id, data, float(body[2]), 0 if len(ident) == 3 else FRAME_EXTENDED))
            elif body[0] == "error":
                append((int(body[1], 16) & 0x1FFFFFFF, bytearray(1), float(body[2]), FRAME_EXTENDED | FRAME_ERROR))
        except ValueError:
            continue  # a frame that does not parse: skipped, the read's others kept
    return out, ""


def frame_message(frame: Frame, channel: str | int | None) -> can.Message:
    """A :data:`Frame` as python-can's socketcand client returns it from ``recv``."""
    can_id, data, stamp, flags = frame
    return can.Message(timestamp=stamp, arbitration_id=can_id, data=data, dlc=len(data),
                       is_extended_id=bool(flags & FRAME_EXTENDED), is_error_frame=bool(flags & FRAME_ERROR),
                       is_rx=True, channel=channel)


def parse_frames(text: str, channel: str | int | None) -> tuple[list[can.Message], str]:
    """:func:`parse_frame_tuples` as ``can.Message``s (python-can's ``recv`` API)."""
    frames, rest = parse_frame_tuples(text)
    return [frame_message(f, channel) for f in frames], rest


#: Where :func:`batch_receive` keeps its reader on the bus (:func:`dispatch_batches` finds it there).
BATCH_READER_ATTRIBUTE = "_rovercan_batch_reader"


class _BatchReader:
    """The receive of one socketcand bus (:func:`batch_receive`); the bus's receive thread's."""

    def __init__(self, bus: can.BusABC, sock: socket.socket) -> None:
        parsed, unparsed = (getattr(bus, name) for name in SOCKETCAND_BUFFERS)
        # what python-can parsed already (its handshake's read)
        self.frames: deque[Frame] = deque((m.arbitration_id, m.data, m.timestamp,
                                           (FRAME_EXTENDED if m.is_extended_id else 0) |
                                           (FRAME_ERROR if m.is_error_frame else 0)) for m in parsed)
        self.rest = str(unparsed)
        self.sock = sock
        self.quickack = bool(getattr(bus, SOCKETCAND_TCP_TUNE, False))
        self.channel = getattr(bus, "channel", None)  # python-can's socketcand client sets it; BusABC does not declare it
        #: takes each read's frames from the deque in order (:func:`dispatch_batches`); None: python-can's recv API
        self.sink: Callable[[deque[Frame]], None] | None = None
        #: told, with when (monotonic) it began, of a wait that came back with nothing (:func:`dispatch_batches`)
        self.on_idle: Callable[[float], None] | None = None
        #: in its ``select``, every frame it read before handed on (:func:`receive_behind`)
        self.waiting = False
        #: the receive low-water mark asked for (:func:`hold_lone_sync`; 1: none), and the mark the
        #: socket has: this thread alone sets it, before each wait: 1 while a read left part of a
        #: frame (the rest of its text may be shorter than the mark, and would wait for the next
        #: frame, the next SYNC), else the one asked for
        self.hold_mark = 1
        self.mark = 1

    def read(self, timeout: float | None) -> bool:
        """One ``select`` and one read into :attr:`frames`; False: nothing came within ``timeout``,
        or the stream ended (python-can's 'no frame': :func:`connection_closed` tells)."""
        sock, on_idle = self.sock, self.on_idle
        began = time.monotonic() if on_idle is not None else 0.0  # before: a hold after the wait proves nothing
        if (mark := 1 if self.rest else self.hold_mark) != self.mark:  # a frame cut in two, whole again, a new hold
            self._set_mark(mark)
        try:
            self.waiting = True  # set after the last read's frames were handed on, cleared before this read
            ready, _, _ = select.select([sock], [], [], timeout)
            self.waiting = False
            if not ready:  # nothing came (a lone SYNC's echo may wait below the low-water mark: no other frame)
                if on_idle is not None:
                    on_idle(began)
                return False
            chunk = sock.recv(RECEIVE_CHUNK_BYTES)
            if self.quickack:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)
        except OSError as err:  # the interface went away: the notifier's error (ReceiveErrors, the supervisor)
            self.waiting = False
            raise can.CanOperationError(f"Failed to receive: {err}") from err
        if not chunk:
            return False
        got, self.rest = parse_frame_tuples(self.rest + chunk.decode("ascii", "replace"))
        self.frames.extend(got)
        return True

    def _set_mark(self, mark: int) -> None:
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT, mark)
            self.mark = mark
        except OSError:  # closed: the read says so
            pass

    def recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        frames, sink = self.frames, self.sink
        if sink is None:  # a frame at a time, as python-can's recv returns them
            if not frames:
                self.read(timeout)
            return (frame_message(frames.popleft(), self.channel) if frames else None), False
        if frames:  # left by a sink that raised (it takes them in order), or read before it was set
            sink(frames)
        deadline = time.monotonic() + timeout if timeout is not None else 0.0
        while self.read(timeout):
            sink(frames)  # a raise leaves the rest in the deque: the notifier's error, then these
            if timeout is None or (timeout := deadline - time.monotonic()) <= 0:
                break
        return None, False


def batch_receive(bus: can.BusABC) -> can.BusABC:
    """A socketcand bus whose receive reads its socket itself: one ``select`` and one read take
    whatever has come (a SYNC period's frames), parsed in one pass (:func:`parse_frame_tuples`).
    Without a sink the next calls return them in order without touching the socket; with one
    (:func:`dispatch_batches`) each read's frames go to it as they are, and ``recv`` returns
    None at its timeout. python-can's own receive did the same work with a debug line formatted
    per read and a WARNING logged for every frame a read cut in two (the bus's receive thread's
    largest cost after the parsing itself, docs/performance.md). The end of the stream is 'no
    frame', as python-can reads it (:func:`connection_closed` tells). Other interfaces are left
    as they are. Returns ``bus``."""
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return bus
    reader = _BatchReader(bus, sock)
    setattr(bus, BATCH_READER_ATTRIBUTE, reader)
    bus._recv_internal = reader.recv_internal  # type: ignore[method-assign]  # this one bus, as pause_when_closed does
    return bus


def dispatch_batches(bus: can.BusABC, sink: Callable[[deque[Frame]], None] | None,
                     on_idle: Callable[[float], None] | None = None) -> bool:
    """Each read of a :func:`batch_receive` bus handed to ``sink`` as it came, without a
    ``can.Message`` or a call of python-can's Notifier per frame: ``sink`` takes the frames from
    the deque in order (what it leaves when it raises comes first at the next read, after the
    notifier's error), and ``recv`` returns None when its timeout passed or the stream ended
    (the Notifier then checks whether it was stopped). Set it before the Notifier runs; None:
    a frame at a time again. ``on_idle`` is called when a wait came back with nothing, with the
    monotonic time that wait began (every frame that had come by then was read). False where
    the bus reads otherwise (a kernel socket: python-can's ``recv``, one ``can.Message`` a frame;
    :func:`watch_idle` then)."""
    reader = getattr(bus, BATCH_READER_ATTRIBUTE, None)
    if not isinstance(reader, _BatchReader):
        return False
    reader.sink, reader.on_idle = sink, on_idle
    return True


def watch_idle(bus: can.BusABC, on_idle: Callable[[float], None]) -> can.BusABC:
    """``on_idle`` called whenever the bus's receive came back with nothing within its timeout
    (python-can's ``_recv_internal``, whose contract is None for a wait with no frame: its
    ``select`` on a kernel socket, a queue's wait on a virtual bus), with the monotonic time that
    wait began, so the receive thread's listener knows when it had read everything that came. For
    a bus that :func:`dispatch_batches` does not read. Watching a bus again replaces the watch
    (a bus handed to a second driver), never stacks it. Returns ``bus``.

    On a kernel socket (python-can's SocketCAN), while a waiter past its deadline asks
    (:func:`receive_behind` sets ``careful_until``), the wait is this function's own ``select``,
    marked, and the bus's receive is called after it with no timeout: python-can's waits and
    reads inside one call, so a thread in it may hold a frame it took from the socket and not yet
    handed on (a starved thread waits for the interpreter right after its ``recvmsg``). Outside
    those seconds a frame costs no more than it did."""
    inner = getattr(bus, _UNWATCHED_RECV, None) or bus._recv_internal
    state = _ReceiveState()
    sock = getattr(bus, "socket", None)
    sock = sock if isinstance(sock, socket.socket) else None

    def recv_internal(timeout: float | None) -> tuple[can.Message | None, bool]:
        began = time.monotonic()  # before: a hold after the wait proves nothing of what came meanwhile
        if sock is not None and began < state.careful_until:
            state.waiting = True  # the frame before was handed on (python-can dispatches it before calling again)
            try:
                ready, _, _ = select.select([sock], [], [], timeout)
            except (OSError, ValueError):
                ready = [sock]  # the bus's own receive says what went wrong, as it would have
            finally:
                state.waiting = False
            got: tuple[can.Message | None, bool] = inner(0.0) if ready else (None, False)
        else:
            got = inner(timeout)
        if got[0] is None:
            on_idle(began)
        return got

    setattr(bus, _UNWATCHED_RECV, inner)
    setattr(bus, _RECEIVE_STATE, state)
    bus._recv_internal = recv_internal  # type: ignore[method-assign]  # this one bus, as batch_receive does
    return bus


#: where :func:`watch_idle` keeps the bus's own ``_recv_internal``, and the state of its receive
_UNWATCHED_RECV = "_rovercan_unwatched_recv"
_RECEIVE_STATE = "_rovercan_receive_state"


#: How long a kernel socket's receive waits in its own marked ``select`` after a waiter asked (s).
CAREFUL_S = 5.0


class _ReceiveState:
    """The receive of a :func:`watch_idle` bus on a kernel socket: until when (monotonic) its
    waits are marked, and whether the receive thread is in such a wait."""

    __slots__ = ("careful_until", "waiting")

    def __init__(self) -> None:
        self.careful_until = 0.0
        self.waiting = False


#: getsockopt's SO_MEMINFO (Linux: the socket's memory; its first word the receive queue's bytes)
_SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)


def _unread_bytes(sock: socket.socket) -> int | None:
    """Bytes waiting in ``sock``'s receive queue (FIONREAD; a socket without it, such as a CAN
    raw socket: the memory its receive queue holds), None when it cannot tell (closed)."""
    try:
        got = fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0")
    except (OSError, ValueError):
        try:
            got = sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 4)
        except (OSError, ValueError):
            return None
    unread: int = struct.unpack("i", got[:4])[0]
    return unread


def receive_behind(bus: can.BusABC | None) -> bool | None:
    """Whether the bus's receive thread has yet to hand on something that has come: it is outside
    its wait (reading, dispatching, or not running), or frames wait in its socket or its batch.
    False: it waits with nothing unread, so every frame that came before this call was handed on
    (the socket is read first, then the thread: one it read meanwhile is either handed on by
    then or keeps the thread outside its wait). On a socketcand bus, less than the socket's
    low-water mark waits without waking it (:func:`hold_lone_sync`: a lone SYNC, never an
    answer). On a kernel socket the thread's waits are marked only from the first call on
    (:func:`watch_idle`): until it is in one, it counts as behind. None: not known (a bus read
    neither by :func:`batch_receive` nor by :func:`watch_idle` on a kernel socket, such as
    python-can's virtual one, or a socketcand server gone: the bus is lost, not the reader
    late). For a waiter past its deadline (motor_driver.process.held.ReadBehind); a system
    call or two, never on the per-frame path."""
    reader = getattr(bus, BATCH_READER_ATTRIBUTE, None)
    if isinstance(reader, _BatchReader):
        if bus is None or connection_closed(bus):
            return None
        unread = _unread_bytes(reader.sock)
        if unread is None:
            return None
        try:
            wakes = reader.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT)
        except OSError:
            return None
        return unread >= wakes or not reader.waiting or bool(reader.frames)
    state = getattr(bus, _RECEIVE_STATE, None)
    sock = getattr(bus, "socket", None)
    if not isinstance(state, _ReceiveState) or not isinstance(sock, socket.socket):
        return None
    state.careful_until = time.monotonic() + CAREFUL_S
    unread = _unread_bytes(sock)
    if unread is None:
        return None
    return unread > 0 or not state.waiting


#: a byte as python-can's socketcand client writes it: lower-case hex, no leading zero
_HEX = tuple(f"{b:x}" for b in range(256))


class DirectSend(NamedTuple):
    """A python-can socketcand bus's send done by this driver (:func:`socketcand_sender`):
    ``send(can_id, data, remote)`` writes one frame; ``text`` is the frame's bytes and ``write`` puts
    several frames' bytes on the socket in one call (:meth:`GuardedNetwork.one_write`)."""

    send: Callable[[int, bytes | bytearray, bool], None]
    text: Callable[[int, bytes | bytearray, bool], bytes]
    write: Callable[[bytes], None]


def socketcand_sender(bus: can.BusABC | None) -> DirectSend | None:
    """A frame written on a python-can socketcand bus's socket as its own ``send`` does (the same
    text: ``convert_can_message_to_ascii_message`` of the ``can.Message`` canopen's ``send_message``
    makes, an id above 0x7FF extended, a remote frame's data dropped as ``can.Message`` drops it
    (socketcand's rawmode has no remote frames); the same TCP_QUICKACK after it when the bus was
    opened with ``tcp_tune``; a socket error raised as it is, a write that blocked SEND_STALL_S as
    :class:`SendStalled`), without building the message,
    formatting python-can's per-send debug line and going through four calls: about a fifth of a
    streamed set-point's Python time (docs/performance.md). The caller holds the network's send
    lock. None for other interfaces (and buses whose ``send`` is not python-can's)."""
    from can.interfaces.socketcand.socketcand import SocketCanDaemonBus

    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if bus is None or not isinstance(sock, socket.socket) or type(bus).send is not SocketCanDaemonBus.send:
        return None
    sendall, setsockopt, hexes = sock.sendall, sock.setsockopt, _HEX.__getitem__
    tune = bool(getattr(bus, SOCKETCAND_TCP_TUNE, False))
    quickack = (socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)

    def text(can_id: int, data: bytes | bytearray, remote: bool) -> bytes:
        if remote:
            data = b""
        ident = f"{can_id & 0x1FFFFFFF:08X}" if can_id > 0x7FF else f"{can_id:03X}"
        return f"< send {ident} {len(data):X} {' '.join(map(hexes, data))} >".encode("ascii")

    def stalled(err: OSError) -> None:
        why = stall_of(bus, err)
        if why:
            raise SendStalled(why) from err

    def write(payload: bytes) -> None:
        try:
            sendall(payload)
        except OSError as err:
            stalled(err)
            raise
        if tune:
            setsockopt(*quickack)

    def send(can_id: int, data: bytes | bytearray, remote: bool) -> None:
        try:
            sendall(text(can_id, data, remote))
        except OSError as err:
            stalled(err)
            raise
        if tune:
            setsockopt(*quickack)

    return DirectSend(send, text, write)


#: socketcand's text of a SYNC (its ``< frame %03X %ld.%06ld  >`` with no data, a Unix-time stamp:
#: socketcand's rawmode and the simulator's server both write it so): 32 bytes until the year 2286.
#: A frame with data is longer; of the rest only a remote frame (no data in rawmode) is as short.
SYNC_TEXT_BYTES = len(f"< frame 080 {2_000_000_000:.6f}  >")


def hold_lone_sync(bus: can.BusABC, hold: bool) -> bool:
    """With ``hold``, a socketcand bus's receive thread wakes only once more than a SYNC's text
    has come (SO_RCVLOWAT): the echo of the driver's own SYNC (the daemon's timer sends it, and it
    reaches this connection as it reaches every other) then waits for the frames that follow it
    (the TPDOs it asks for, within its period) instead of waking the thread alone, about a third
    of its wake-ups (docs/performance.md). Any frame with data wakes it at once, and so does the
    end of the connection; only a frame without data (SYNC, a remote frame) waits, for the next
    frame. A frame whose text a read cut in two is read whole at once: a batch reader (its
    receive thread, the socket's mark's one writer) takes the mark asked for at its next wait,
    and 1 while a frame is cut (the rest can be shorter). Without ``hold``: every byte wakes it.
    Returns False where there is no such socket (other interfaces: nothing to do) or it is closed."""
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, None)
    if not isinstance(sock, socket.socket):
        return False
    mark = SYNC_TEXT_BYTES + 1 if hold else 1
    reader = getattr(bus, BATCH_READER_ATTRIBUTE, None)
    if isinstance(reader, _BatchReader):  # within its wait's timeout (the notifier's, 0.1 s)
        reader.hold_mark = mark
        return sock.fileno() != -1
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT, mark)
    except OSError:
        return False
    return True


#: python-can's loggers that put traceback text into their records when a bus goes away.
TRACEBACK_LOGGERS = ("can.interfaces.socketcand.socketcand", "can.bcm")



class _OneLine(logging.Filter):
    """Turns a record of python-can's that carries a traceback into a DEBUG line without it: the
    driver says the loss itself, once (the supervisor's "bus ... lost (why)")."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if record.exc_info or "Traceback" in text or record.name == "can.bcm":
            record.msg, record.args = text.split("Traceback (most recent call last)")[0].strip(), None
            record.exc_info = record.exc_text = None
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


_ONE_LINE = _OneLine()


def quiet_dependency_tracebacks() -> None:
    """python-can's records of a lost bus become one DEBUG line each (idempotent)."""
    for name in TRACEBACK_LOGGERS:
        dependency = logging.getLogger(name)
        if _ONE_LINE not in dependency.filters:
            dependency.addFilter(_ONE_LINE)


class ReceiveErrors(can.Listener):  # type: ignore[misc]
    """Takes the receive thread's error (python-can's Notifier then keeps it in ``exception``,
    where the supervisor finds it, instead of re-raising it in its thread with a traceback)."""

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        logger.debug("receive failed: %s", brief_error(exc))

    def stop(self, *args: Any) -> None:
        pass


class ElevenBitListener(canopen.network.MessageListener):  # type: ignore[misc]
    """canopen's frame listener for CANopen's own frames only: CiA 301 uses 11-bit identifiers,
    and canopen dispatches an extended frame by its identifier alone (an extended 0x181 carrying
    0x0627 read as the drive's statusword: a false Operation Enabled)."""

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id:
            return
        super().on_message_received(msg)


#: The frames :meth:`GuardedNetwork.one_write` holds: RPDOs (RPDO1-4 of every node). Any other (an
#: SDO request the thread then waits an answer for, NMT, a heartbeat) writes the held ones and goes out.
HELD_IDS = (0x200, 0x57F)

#: A full transmit queue (ENOBUFS) is retried for this long, pausing this long between tries: a
#: real controller's queue of 10 frames drains in about 1.3 ms at 1 Mbit/s.
TX_QUEUE_FULL_RETRY_S = 0.02
TX_QUEUE_FULL_PAUSE_S = 0.0005


#: python-can's SocketCAN ``send`` (no timeout: canopen's) when the socket is not writable: the
#: frames waiting in the interface's queue fill the socket's send buffer (half of it, about 100-200
#: frames) before a queue of the default 1000 refuses one with ENOBUFS. The same full queue, with
#: no errno: pinned by tests/test_adapters.py against the installed python-can.
SOCKETCAN_BUFFER_FULL = "Transmit buffer full"


def queue_full(err: BaseException) -> bool:
    """The kernel refused a send because the interface's transmit queue is full (ENOBUFS, or a
    SocketCAN socket not writable for the frames waiting in it: :data:`SOCKETCAN_BUFFER_FULL`)."""
    if isinstance(err, can.CanOperationError) and err.error_code is None and str(err) == SOCKETCAN_BUFFER_FULL:
        return True
    code = getattr(err, "error_code", None) if isinstance(err, can.CanError) else getattr(err, "errno", None)
    return code == errno.ENOBUFS or (isinstance(err.__cause__, OSError) and err.__cause__.errno == errno.ENOBUFS)


#: A frame rejection (callback and cause) is logged at most once every this long.
REJECTED_LOG_PERIOD_S = 10.0


class HeldFramesLost(can.CanOperationError):  # type: ignore[misc]
    """Frames held by :meth:`GuardedNetwork.one_write` were not written (their write failed, or
    their bus was replaced by a reconnect): raised to the holder at the end of its block, with
    their CAN IDs (``can_ids``: whose commands were lost)."""

    def __init__(self, message: str, can_ids: tuple[int, ...] = ()) -> None:
        super().__init__(message)
        self.can_ids = can_ids


@dataclass(frozen=True)
class Rejected:
    """Frames of one node a receive callback raised on: how many, the newest cause (``callback:
    Type: text``) and when (the receive thread's monotonic clock)."""

    count: int
    cause: str
    at: float


class GuardedNetwork(canopen.Network):
    """A canopen Network whose frame dispatch survives a failing callback.

    canopen's own consumers (EMCY, NMT) raise on malformed frames (a 2-byte EMCY, an empty NMT
    command: found by the random-frame test), and an exception in the receive thread stops
    python-can's Notifier, i.e. the driver would go deaf from one bad frame. Here each callback
    is isolated; a rejected frame is counted per node (:meth:`rejected`: the count and the newest
    cause, for /diagnostics) and logged with its cause at a bounded rate (one line per callback and
    cause every REJECTED_LOG_PERIOD_S, with the count held back). The receive thread alone writes
    the counts (one assignment of an immutable :class:`Rejected` per node).
    """

    def __init__(self, bus: can.BusABC | None = None, listeners: tuple[can.Listener, ...] = (),
                 on_sent: Callable[[int, bytes | bytearray, bool], None] | None = None) -> None:
        super().__init__(bus)
        # before connect(): its Notifier takes the list
        self.listeners: list[can.Listener] = [ElevenBitListener(self), *listeners]
        self.rejected_frames = 0
        self._rejected: dict[int, Rejected] = {}  # node id (the COB-ID's low 7 bits) -> its rejections
        self._rejected_log = Throttle(REJECTED_LOG_PERIOD_S)
        #: called with each frame sent (the flight recorder), after it went out: (id, data, remote)
        self.on_sent = on_sent
        #: sends the kernel refused with ENOBUFS (a full transmit queue: a real controller's
        #: qlen is 10), each retried (the host heartbeat's counted here too, not retried); and
        #: the frames given up on after TX_QUEUE_FULL_RETRY_S
        self.tx_queue_full = 0
        self.tx_queue_dropped = 0
        # the bus the direct sender was made for, and it (socketcand_sender; None: canopen's send)
        self._sender: tuple[can.BusABC | None, DirectSend | None] = (None, None)
        # one_write's, under the send lock: the thread whose frames are held, the bus they are for,
        # their bytes and the frames (for on_sent once written)
        self._holder: int | None = None
        self._held_lost: str | None = None  # why frames held in the current block were not written
        self._held_lost_ids: list[int] = []  # and their CAN IDs
        self.held_dropped = 0  # held frames not written: their bus was replaced (a reconnect) meanwhile
        self._held_for: can.BusABC | None = None
        self._held: list[bytes] = []
        self._held_frames: list[tuple[int, bytes | bytearray, bool]] = []

    def listen_with(self, listener: can.Listener) -> None:
        """Before :meth:`connect`: ``listener`` is the receive thread's one listener, in place of
        canopen's and the 11-bit filter (it dispatches the 11-bit frames to :meth:`notify` itself:
        motor_driver.bus.handle.FrameDispatch)."""
        self.listeners = [listener]

    def count_queue_full(self) -> None:
        """A send refused with ENOBUFS that was not retried (the host heartbeat's)."""
        self.tx_queue_full += 1

    def send_message(self, can_id: int, data: bytes | bytearray, remote: bool = False) -> None:
        deadline = 0.0
        while True:
            try:
                held = self._send_once(can_id, data, remote)
                break
            except (can.CanError, OSError) as err:
                if not queue_full(err):
                    raise
                self.tx_queue_full += 1
                now = time.monotonic()
                deadline = deadline or now + TX_QUEUE_FULL_RETRY_S
                if now >= deadline:  # nothing drains it (no node acknowledges): the caller decides
                    self.tx_queue_dropped += 1
                    raise can.CanOperationError(f"the transmit queue stayed full for {TX_QUEUE_FULL_RETRY_S * 1000:.0f}"
                                                f" ms (ENOBUFS); frame 0x{can_id:03X} not sent: is any node"
                                                " acknowledging? check cabling, termination and bitrate",
                                                errno.ENOBUFS) from err
                time.sleep(TX_QUEUE_FULL_PAUSE_S)  # a frame's time at 1 Mbit/s is about 0.1 ms
        hook = self.on_sent
        if hook is not None and not held:  # a held frame's once it is written
            hook(can_id, data, remote)

    def _direct(self) -> tuple[can.BusABC | None, DirectSend | None]:
        """The bus and its direct sender (socketcand_sender; None: canopen's send), made again for
        each bus this network is given (a reconnect)."""
        bus = self.bus
        made_for, send = self._sender
        if bus is not made_for:
            send = socketcand_sender(bus)
            self._sender = (bus, send)
        return bus, send

    def _send_once(self, can_id: int, data: bytes | bytearray, remote: bool) -> bool:
        """canopen's ``send_message`` (its lock, its check of the receive thread after), through the
        socketcand socket directly where the bus is python-can's socketcand client. True: the frame
        is held (an RPDO of this thread's :meth:`one_write`); any other frame writes the held ones first."""
        bus = self.bus
        made_for, direct = self._sender
        if bus is not made_for:
            bus, direct = self._direct()
        if direct is None or bus is None:
            super().send_message(can_id, data, remote)
            return False
        written: list[tuple[int, bytes | bytearray, bool]] | None = None
        with self.send_lock:
            if self._holder is not None:
                if self._holder == threading.get_ident() and bus is self._held_for and HELD_IDS[0] <= can_id <= HELD_IDS[1]:
                    self._held.append(direct.text(can_id, data, remote))
                    self._held_frames.append((can_id, data, remote))
                    return True
                written = self._write_held(direct)  # the order on the wire is the order of the calls
            direct.send(can_id, data, remote)
        if written:
            self._told(written)  # outside the lock, before this frame's (send_message's)
        self.check()
        return False

    @contextmanager
    def one_write(self) -> Iterator[None]:
        """The RPDOs this thread sends inside go out in one write of the socket, at the end, where the
        bus is python-can's socketcand client (elsewhere, nested, or while another thread holds, each
        as it is sent): a SYNC period's set-points of several drives for one system call, one TCP
        segment and one wake-up of the daemon instead of one each (docs/performance.md). The wire
        keeps the order of the calls: any other frame (another thread's stop, this thread's SDO,
        whose answer it waits for) first writes what is held. A frame held is told to ``on_sent``
        once written. Held frames not written (a failed write, or a bus replaced by a reconnect: the
        frames were for the old connection and are dropped, counted) raise at the end."""
        bus, direct = self._direct()
        with self.send_lock:
            holds = direct is not None and bus is not None and self._holder is None
            if holds:
                self._holder, self._held_for, self._held_lost, self._held_lost_ids = threading.get_ident(), bus, None, []
        if not holds or direct is None:
            yield
            return
        try:
            yield
        finally:
            with self.send_lock:
                self._holder = None
                try:
                    written = self._write_held(direct)
                except Exception:  # the write failed: in _held_lost, raised below as the frames' loss
                    written = []
                lost, lost_ids = self._held_lost, tuple(self._held_lost_ids)
            self._told(written)
            if lost is not None:
                raise HeldFramesLost(lost, lost_ids)
            self.check()  # the frames were written: whatever it raises is the bus's, not theirs

    @staticmethod
    @contextmanager
    def each_one_write(networks: Iterable[tuple[str, GuardedNetwork]]) -> Iterator[list[tuple[str, Exception]]]:
        """:meth:`one_write` on several buses at once (``networks``: name, network): each bus's RPDOs
        sent inside go out in one write at the end, each bus written whatever the others' write did.
        The list yielded is filled at the end with the buses that failed, each with its error: its
        held frames not written (:class:`HeldFramesLost`, naming them: a failed write, a reconnect),
        or written and the bus then found broken (its receive thread's error, ``check()``), for the
        caller to say which commands were lost and to raise what it does not expect."""
        failed: list[tuple[str, Exception]] = []
        held: list[tuple[str, AbstractContextManager[None]]] = []
        try:
            for name, network in networks:
                block = network.one_write()
                block.__enter__()
                held.append((name, block))
            yield failed
        finally:
            for name, each in held:
                try:
                    each.__exit__(None, None, None)
                except Exception as err:  # every bus written first; the caller says it
                    failed.append((name, err))

    def _write_held(self, direct: DirectSend) -> list[tuple[int, bytes | bytearray, bool]]:
        """Under the send lock: the frames held, in one write; the frames written (for ``on_sent``).
        Frames held for a bus since replaced are dropped (counted), and frames whose write failed are
        lost (the error raised here, to this sender): either said to the holder at its end."""
        if not self._held:
            return []
        payload, frames, self._held, self._held_frames = b"".join(self._held), self._held_frames, [], []
        if self.bus is not self._held_for:
            self._lose(frames, "for a bus since replaced (a reconnect) not sent")
            return []
        try:
            direct.write(payload)
        except Exception as err:
            self._lose(frames, f"not sent: {err}")
            raise
        return frames

    def _lose(self, frames: list[tuple[int, bytes | bytearray, bool]], why: str) -> None:
        """Under the send lock: held ``frames`` not written, counted and kept for the holder's end."""
        self.held_dropped += len(frames)
        self._held_lost = f"{len(frames)} frame(s) held {why}"
        self._held_lost_ids.extend(can_id for can_id, _, _ in frames)

    def _told(self, frames: list[tuple[int, bytes | bytearray, bool]]) -> None:
        hook = self.on_sent
        if hook is not None:
            for frame in frames:
                hook(*frame)

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        callbacks = self.subscribers.get(can_id)
        if callbacks:
            for callback in callbacks:
                try:
                    callback(can_id, data, timestamp)
                except Exception as err:  # a malformed frame must not stop the receive thread
                    self._reject(can_id, data, callback, err)
        self.scanner.on_message_received(can_id)

    def _reject(self, can_id: int, data: bytearray, callback: Callable[..., object], err: Exception) -> None:
        """Receive thread: a frame a callback raised on, counted for its node and logged (bounded)."""
        self.rejected_frames += 1
        where = str(getattr(callback, "__qualname__", callback))
        cause = f"{where}: {type(err).__name__}: {err}"
        node = can_id & 0x7F
        before = self._rejected.get(node)
        self._rejected[node] = Rejected(before.count + 1 if before else 1, cause, time.monotonic())
        passed = self._rejected_log.admit((where, type(err)))
        if passed is not None:
            logger.warning("frame 0x%03X %s rejected by %s: %s: %s (%d frame(s) of node %d rejected so far%s)",
                           can_id, bytes(data).hex(), where, type(err).__name__, err, self._rejected[node].count,
                           node, f"; {passed[0]} like this not logged in the last {passed[1]:.0f} s"
                           if passed[0] else "")

    def rejected(self, node_id: int) -> Rejected | None:
        """The frames of ``node_id`` a receive callback raised on (None: none)."""
        return self._rejected.get(node_id)

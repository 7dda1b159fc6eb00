"""The wire's time: bit timing of classic CAN frames (the shared passive definition in
:mod:`can_config.bits`), and when a frame reached the bus.

A frame that comes to the server over a socket (a client's, or a tick of the broadcast manager's
timer process) reached the bus when its bytes reached the socket: Linux's ``SO_TIMESTAMPNS``
(the socket module does not name it) gives every read that time, and the frame is stamped with
it, as a CAN controller stamps a frame on the wire, not with the moment this server's interpreter
got round to it (its drive threads can hold it for a tick).

Owner: none; pure functions of a frame and the wire's timing.
"""

from __future__ import annotations

import socket
import struct
import sys
import time

from can_config.bits import frame_bits, frame_time_s

__all__ = ["ARRIVAL_ANCILLARY_BYTES", "arrival_time", "frame_bits", "frame_time_s", "stamp_arrivals",
           "tcp_bytes_received"]

_SO_TIMESTAMPNS: int | None = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform == "linux" else None)
_TIMESPEC = struct.Struct("@ll")
#: The ancillary buffer a ``recvmsg`` needs for the stamp.
ARRIVAL_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)


#: ``struct tcp_info`` (linux/tcp.h, Linux 4.1 on): ``tcpi_bytes_received``, a u64 at this offset.
_TCP_INFO_BYTES_RECEIVED = struct.Struct("@Q")
_TCP_INFO_BYTES_RECEIVED_AT = 128
_TCP_INFO = getattr(socket, "TCP_INFO", 11) if sys.platform == "linux" else None  # elsewhere another layout


def tcp_bytes_received(sock: socket.socket) -> int | None:
    """The bytes the kernel has received on a TCP socket so far, whatever this process read of
    them (None where it does not say: not Linux, an older kernel, not TCP, closed)."""
    if _TCP_INFO is None:
        return None
    end = _TCP_INFO_BYTES_RECEIVED_AT + _TCP_INFO_BYTES_RECEIVED.size
    try:
        info = sock.getsockopt(socket.IPPROTO_TCP, _TCP_INFO, end)
    except OSError:
        return None
    return _TCP_INFO_BYTES_RECEIVED.unpack_from(info, _TCP_INFO_BYTES_RECEIVED_AT)[0] if len(info) >= end else None


def stamp_arrivals(sock: socket.socket) -> None:
    """Ask the kernel to stamp every read of ``sock`` (where it can; else frames are stamped
    when read)."""
    if _SO_TIMESTAMPNS is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            pass


def arrival_time(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's arrival time of a read (``time.time()``'s clock), or now where it gave none."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return float(sec + nsec * 1e-9)
    return time.time()

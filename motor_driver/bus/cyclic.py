"""A cyclic frame (the SYNC) sent by the bus daemon's timer instead of a thread of ours.

python-can's ``send_periodic`` on a SocketCAN interface hands the frame to the kernel's
broadcast manager; on a socketcand bus it runs a Python thread, whose period then depends on
how soon this interpreter lets it run (a busy process, the GIL: SYNC period errors of 1-2 ms at
p99 measured on two cores). socketcand has the broadcast manager too: ``< add SEC USEC ID LEN
.. >`` on a connection in BCM mode makes the daemon send the frame on its own timer (the
kernel's, on a real socketcand; the simulator's server runs one of its own). The job ends when
that connection closes, so a SYNC of a dead driver stops as it did before.

A BCM connection sends nothing after its ``< add >``; a bus server short of connection slots
may close clients silent for a while (the simulator's: 60 s, oldest first). So the task sends
``< echo >`` every ``KEEPALIVE_S`` (``keep_alive()``, called by the driver's supervisor) and
reports a connection the daemon closed.

:class:`DaemonCyclicTask` opens that connection, adds the job and deletes it on ``stop()``.
"""

from __future__ import annotations

import logging
import select
import socket
import time

import can

from can_config.errors import BusLostError
from motor_driver.process.held import POLL_S, HeldDeadline

logger = logging.getLogger(__name__)

#: How long the daemon has to greet, open the channel and (for an error) answer the job.
DAEMON_REPLY_TIMEOUT_S = 2.0
#: After '< add >', an error reply would come within this long (the daemon answers nothing else).
ADD_ERROR_WAIT_S = 0.05
#: A BCM connection says ``< echo >`` this often, so that a server never takes it for idle.
KEEPALIVE_S = 10.0


def add_command(msg: can.Message, period_s: float) -> str:
    """The socketcand line that makes the daemon send ``msg`` every ``period_s``."""
    usec_total = round(period_s * 1e6)
    sec, usec = divmod(usec_total, 1_000_000)
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = " ".join(f"{b:02X}" for b in msg.data)
    return f"< add {sec} {usec} {can_id} {len(msg.data)} {data} >".replace("  ", " ")


class DaemonCyclicTask:
    """One cyclic job in a socketcand daemon, on a connection of its own. ``stop()`` is
    idempotent; raises :class:`BusLostError` when the daemon cannot be reached or refuses."""

    def __init__(self, host: str, port: int, channel: str, msg: can.Message, period_s: float,
                 timeout_s: float = DAEMON_REPLY_TIMEOUT_S) -> None:
        self.where = f"socketcand {host}:{port} {channel}"
        self._can_id = msg.arbitration_id
        self._buf = b""
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as err:
            raise BusLostError(f"{self.where}: cannot connect for the cyclic SYNC job: {err}") from err
        self._sock: socket.socket | None = sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._expect("< hi >", timeout_s)
            sock.sendall(f"< open {channel} >".encode("ascii"))
            self._expect("< ok >", timeout_s)
            sock.sendall(add_command(msg, period_s).encode("ascii"))
            readable, _, _ = select.select([sock], [], [], ADD_ERROR_WAIT_S)
            if readable:
                raise BusLostError(f"{self.where}: the daemon refused the cyclic job: {self._line(timeout_s)}")
        except (OSError, BusLostError) as err:
            self.stop()
            if isinstance(err, BusLostError):
                raise
            raise BusLostError(f"{self.where}: cyclic job not set up: {err}") from err
        self._last_said = time.monotonic()
        logger.info("%s: 0x%03X every %.1f ms by the daemon's timer", self.where, self._can_id, period_s * 1000)

    def keep_alive(self, now: float) -> bool:
        """``< echo >`` when the connection has been silent ``KEEPALIVE_S``, and drop what the
        daemon said since (its echoes); False when the daemon closed the connection (the job is
        gone with it). Called by one thread (the driver's supervisor); never blocks."""
        sock = self._sock
        if sock is None:
            return False
        try:
            while select.select([sock], [], [], 0)[0]:
                chunk = sock.recv(4096, socket.MSG_DONTWAIT)
                if not chunk:
                    logger.error("%s: the daemon closed the cyclic job's connection", self.where)
                    return False
                if b"error" in chunk:
                    logger.warning("%s: the daemon said %r", self.where, chunk[:80])
            if now - self._last_said >= KEEPALIVE_S:
                sock.send(b"< echo >", socket.MSG_DONTWAIT)
                self._last_said = now
        except BlockingIOError:
            pass  # the daemon is slow to read: the next call tries again
        except OSError as err:
            logger.error("%s: cyclic job's connection failed: %s", self.where, err)
            return False
        return True

    def _line(self, timeout_s: float) -> str:
        assert self._sock is not None
        deadline = HeldDeadline(timeout_s)  # a reply that came while this process was held is a reply
        while b">" not in self._buf:
            remaining = deadline.remaining()
            if remaining <= 0:
                raise BusLostError(f"{self.where}: no reply within {timeout_s:g} s{deadline.said()}")
            self._sock.settimeout(min(remaining, POLL_S))
            try:
                chunk = self._sock.recv(256)
            except TimeoutError:
                continue
            if not chunk:
                raise BusLostError(f"{self.where}: the daemon closed the connection")
            self._buf += chunk
        self._sock.settimeout(timeout_s)  # the sends after it: the caller's bound, not a poll's
        line, _, self._buf = self._buf.partition(b">")
        return (line + b">").decode("ascii", "replace").strip()

    def _expect(self, wanted: str, timeout_s: float) -> None:
        line = self._line(timeout_s)
        if line != wanted:
            raise BusLostError(f"{self.where}: expected {wanted!r}, got {line!r}")

    def stop(self) -> None:
        sock, self._sock = self._sock, None
        if sock is None:
            return
        try:
            sock.sendall(f"< delete {self._can_id:03X} >".encode("ascii"))
        except OSError:
            pass  # a closed connection ends the job as well
        finally:
            sock.close()

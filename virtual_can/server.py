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
timer runs on a real socketcand; here a timer process of the server's (:mod:`virtual_can.bcm_timer`) does::

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

What lives where: :mod:`virtual_can.client` (one client: protocol, reader, writer),
:mod:`virtual_can.cyclic_jobs` (the BCM timer), this module (accepting clients, slots).
"""

from __future__ import annotations

import logging
import socket
import threading
import time

from can_config.errors import SimError
from can_config.model import SOCKETCAND_PORT
from can_config.realtime import SIM_PRIORITY, ensure_thread_realtime
from virtual_can.client import CLIENT_QUEUE_BYTES, RAWMODE_HOLD_S, SLOW_CLIENT_DROP_LIMIT, Client, format_frame, parse_send
from virtual_can.cyclic_jobs import CYCLIC_JOBS_PER_CLIENT, CYCLIC_JOBS_TOTAL, POLL_S, CyclicJobError, CyclicJobs
from virtual_can.engine import BusEngine

logger = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = SOCKETCAND_PORT
DEFAULT_MAX_CLIENTS = 64
#: A client that has not reached rawmode (nor added a cyclic job) this long after connecting is
#: closed (idle connections would otherwise hold every client slot).
HANDSHAKE_TIMEOUT_S = 5.0
#: With every slot taken, a new client gets the slot of the client idle longest, when that one
#: has sent no frame and no command for this long, nor its cyclic jobs a frame: an ``< echo >``
#: keeps a connection open but does not hold a slot against a newcomer (64 clients echoing every
#: 20 s held every slot for ever). The driver's SYNC job sends every period: never idle.
IDLE_TIMEOUT_S = 60.0
_LOOPBACK = ("127.0.0.1", "localhost", "::1")


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
        self._clients: set[Client] = set()
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
    def clients(self) -> list[Client]:
        with self._lock:
            return list(self._clients)

    def on_bus_until(self, wall: float) -> float:
        """The bus time up to which every client's frames are on the bus, asked at ``wall``
        (:meth:`Client.on_bus_until`): the drives judge a silence on no later time."""
        return min([wall, *(client.on_bus_until(wall) for client in self.clients)])

    def _accept_loop(self) -> None:
        # the clients' reader and writer threads start from this one and inherit its scheduling: the
        # bus's stamps and deliveries go on however busy the machine is (below the driver's priority)
        ensure_thread_realtime(f"bus server on port {self.port}", SIM_PRIORITY)
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
        client = Client(self, sock, addr)
        with self._lock:
            self._clients.add(client)
        client.start()

    def _free_an_idle_slot(self, newcomer: tuple[str, int]) -> bool:
        """Slots full: close the client idle longest (no frame and no command but echoes, and no
        frame of its cyclic jobs), if idle for ``idle_timeout_s`` (see IDLE_TIMEOUT_S)."""
        now = time.monotonic()
        with self._lock:
            clients = list(self._clients)
        idle_s = {c: now - max(c.last_active, self.cyclic.last_sent(c)) for c in clients}
        idle = max(clients, key=idle_s.__getitem__, default=None)
        if idle is None or idle_s[idle] < self.idle_timeout_s:
            return False
        logger.info("slots full: closing client %s (no frame or command for %.0f s) to admit %s", idle.addr,
                    idle_s[idle], newcomer)
        idle.close()
        self.idle_closed += 1
        return True

    def forget(self, client: Client) -> None:
        """A closed client's slot is free (the client calls it as it closes)."""
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


# the names callers imported from here before the split
__all__ = ["CLIENT_QUEUE_BYTES", "CYCLIC_JOBS_PER_CLIENT", "CYCLIC_JOBS_TOTAL", "DEFAULT_HOST", "DEFAULT_MAX_CLIENTS",
           "DEFAULT_PORT", "RAWMODE_HOLD_S", "SLOW_CLIENT_DROP_LIMIT", "CyclicJobError", "SocketcandServer", "format_frame",
           "parse_send"]

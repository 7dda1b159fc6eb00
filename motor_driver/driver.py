"""The motor driver: every configured bus and drive in one process.

Per bus: a python-can bus (opened from config, or given), a canopen ``Network`` (its notifier
thread runs the PDO callbacks), a SYNC producer outside this interpreter where the bus has a
timer of its own (the socketcand daemon's cyclic job, :mod:`motor_driver.cyclic`; the kernel's
BCM through python-can's periodic send on SocketCAN; else python-can's thread), and a worker
thread for the bus's blocking jobs (re-boot of a drive that reset, reconnection of a lost bus).

Threads and what they own:
- the notifier thread of each bus (canopen/python-can): decodes frames into each Drive's
  received state and notifies waiters; it sends nothing but the set-point handshake's reply.
- the supervisor thread (``rovercan-supervisor``), period SUPERVISOR_PERIOD_S, never blocks:
  produces the host heartbeat on every bus, checks the drives' heartbeats, runs the velocity
  watchdog and the limit guard, notices lost buses and hands re-boots and reconnects to the
  bus's worker. It owns ``bus_lost`` and each BusHandle's reconnect bookkeeping.
- one worker per bus (``rovercan-<bus>``): the re-boots and reconnects, one at a time.
- the caller's threads: commands, each serialised per drive by the Drive's lock.
- the flight recorder's writer (``rovercan-recorder``, :mod:`motor_driver.recorder`): the
  others append frames, states and incidents to it without waiting; it writes the files.

The host heartbeat (node ``host_node_id``, every ``host_heartbeat_ms``) is sent by the
supervisor loop itself, not by a kernel timer: it proves that the driver is alive, so a killed,
hung or stopped process falls silent and every drive, told at boot to watch it (0x1016, 0x6007),
stops by itself within its consumer time.

Safe by default: start() boots and configures but enables only drives with
``arm_on_start``; close() quick-stops and disables every drive, stops SYNC, stops threads,
and closes the buses it opened, in that order.
"""

from __future__ import annotations

import functools
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Collection, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import can

from can_config import RoverConfig, load_drive_od
from can_config.bits import frame_bits
from can_config.config import BusConfig
from can_config.errorframes import ErrorFrame, decode_error_frame
from can_config.errors import BusLostError, ConfigError, ForeignMasterError, MotorError
from can_config.objects import NmtState
from motor_driver.adapters import GuardedNetwork, connection_closed
from motor_driver.busload import MAX_LOAD, WARN_LOAD, plan_load
from motor_driver.cia402 import State
from motor_driver.cyclic import DaemonCyclicTask
from motor_driver.drive import Drive, DriveState
from motor_driver.recorder import FlightRecorder

logger = logging.getLogger(__name__)

SUPERVISOR_PERIOD_S = 0.01
#: Another master's frames mark its drives for this long; the mark clears after this much quiet.
FOREIGN_HOLD_S = 0.5
#: Window in which SYNC frames are counted when the bus daemon sends the driver's own.
SYNC_RATE_WINDOW_S = 0.3
FOREIGN_RELEASE_S = 2.0
#: Before its first NMT command the driver (and each bench command) listens this long, at least,
#: for another master: two periods of the host heartbeat, if longer (:func:`look_for_master`).
LOOK_MIN_S = 0.2
RECONNECT_MIN_S = 0.2
#: Host heartbeats that could not be sent in a row (their periods) before the bus counts as lost.
SEND_FAILING_BEATS = 3
#: A receive that failed is tried again after this pause (python-can's notifier loops on).
RX_ERROR_PAUSE_S = 0.05
RECONNECT_MAX_S = 5.0
NOTIFIER_TIMEOUT_S = 0.1
#: Tries to open a bus whose handshake failed (a socketcand daemon's first frame can arrive with
#: its rawmode '< ok >', which python-can's client rejects); other errors are not retried.
OPEN_ATTEMPTS = 3
OPEN_RETRY_S = 0.1
#: How long the driver waits for a socketcand server to accept, and its back-off between tries.
CONNECT_TIMEOUT_S = 10.0
CONNECT_RETRY_MIN_S = 0.1
CONNECT_RETRY_MAX_S = 2.0
#: How long a socketcand server may take to greet and to finish the handshake (it takes ms).
HANDSHAKE_TIMEOUT_S = 3.0


class _QuietConnectRetries(logging.Filter):
    """python-can's socketcand client retries its connect in a loop without a pause and logs
    every failure (30,000 lines a second while a server is down): those lines are dropped;
    :func:`wait_for_server` says the same once per attempt, with back-off."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Failed to connect to server")


logging.getLogger("can.interfaces.socketcand.socketcand").addFilter(_QuietConnectRetries())


def _greeting(sock: socket.socket, timeout_s: float) -> str:
    """What a server says first (a socketcand server: ``< hi >``), or '' after ``timeout_s``."""
    sock.settimeout(timeout_s)
    try:
        return sock.recv(64).decode("ascii", "replace")
    except TimeoutError:
        return ""


def wait_for_server(host: str, port: int, timeout_s: float) -> None:
    """Until a socketcand server at host:port accepts and greets (``< hi >``): one attempt at a
    time, backing off from CONNECT_RETRY_MIN_S to CONNECT_RETRY_MAX_S, one log line per failed
    attempt; then :class:`BusLostError` naming host:port and the likely cause. The greeting is
    checked because python-can's handshake reads without a timeout: a port that accepts and stays
    silent (another service, a hung daemon) would hang the caller for ever."""
    deadline = time.monotonic() + timeout_s
    delay = CONNECT_RETRY_MIN_S
    attempt = 0
    while True:
        attempt += 1
        try:
            with socket.create_connection((host, port), timeout=max(0.05, min(1.0, deadline - time.monotonic()))) as sock:
                said = _greeting(sock, HANDSHAKE_TIMEOUT_S)
            if said.startswith("< hi >"):
                return
            verdict = "no socketcand server"
            why = (f"it accepted but sent {said[:40]!r}, not the socketcand greeting '< hi >'" if said else
                   f"it accepted but sent no socketcand greeting ('< hi >') within {HANDSHAKE_TIMEOUT_S:g} s")
        except OSError as err:
            verdict = "not reachable"
            why = err.strerror or str(err) or type(err).__name__
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise BusLostError(f"socketcand server {host}:{port} {verdict} ({why}) after {attempt} attempt(s)"
                               f" in {timeout_s:g} s; is the simulator running (rovercan sim) or socketcand"
                               " started, and are host and port right?")
        # each attempt at INFO: a waiting driver says so in its log; a command gets the one line of
        # the final error (a WARNING per attempt was five lines for a refused connection)
        logger.info("socketcand server %s:%d: %s (attempt %d); next try in %.1f s", host, port, why, attempt,
                    min(delay, remaining))
        time.sleep(min(delay, remaining))
        delay = min(delay * 2, CONNECT_RETRY_MAX_S)


def _bus_within(kwargs: dict[str, Any], timeout_s: float) -> can.BusABC:
    """``can.Bus(**kwargs)`` on a helper thread, given up after ``timeout_s`` with
    :class:`BusLostError` (python-can's socketcand handshake has no timeout of its own). A bus
    that opens after it was given up is shut down by the helper."""
    outcome: list[can.BusABC | BaseException] = []
    given_up = threading.Event()
    lock = threading.Lock()  # outcome vs. given_up: the helper either hands the bus over or shuts it

    def open_it() -> None:
        try:
            result: can.BusABC | BaseException = can.Bus(**kwargs)
        except BaseException as err:  # handed to the caller's thread
            result = err
        with lock:
            if given_up.is_set():
                if isinstance(result, can.BusABC):
                    result.shutdown()
                return
            outcome.append(result)

    helper = threading.Thread(target=open_it, name="rovercan-open-bus", daemon=True)
    helper.start()
    helper.join(timeout_s)
    with lock:
        if not outcome:
            given_up.set()
            raise BusLostError(f"bus {kwargs.get('channel')} at {kwargs.get('host')}:{kwargs.get('port')}: the"
                               f" socketcand handshake did not finish within {timeout_s:g} s; the server"
                               " accepted but stopped answering (restart it)")
    result = outcome[0]
    if isinstance(result, BaseException):
        raise result
    return result


def open_bus(kwargs: dict[str, Any], connect_timeout_s: float = CONNECT_TIMEOUT_S) -> can.BusABC:
    """``can.Bus(**kwargs)``, retrying a failed protocol handshake (``can.CanError``) a few times.
    A socketcand server is first waited for (:func:`wait_for_server`), so python-can's own
    connect loop never spins, and its handshake is bounded by HANDSHAKE_TIMEOUT_S."""
    socketcand = kwargs.get("interface") == "socketcand" and "host" in kwargs and "port" in kwargs
    if socketcand:
        wait_for_server(str(kwargs["host"]), int(kwargs["port"]), connect_timeout_s)

    def opened() -> can.BusABC:
        return _bus_within(kwargs, HANDSHAKE_TIMEOUT_S) if socketcand else can.Bus(**kwargs)

    for attempt in range(1, OPEN_ATTEMPTS):
        try:
            return opened()
        except can.CanError as err:
            logger.warning("bus %s: opening failed (%s); try %d of %d", kwargs.get("channel"), err,
                           attempt + 1, OPEN_ATTEMPTS)
            time.sleep(OPEN_RETRY_S)
    return opened()


class BusStats(can.Listener):
    """Frames received on a bus, error frames, and the load they make (worst-case bits)."""

    def __init__(self, bitrate: int) -> None:
        self.bitrate = bitrate
        self.frames = 0
        self.error_frames = 0
        #: the newest error frame: (monotonic time, decoded); and the newest that loses the bus
        #: (bus-off, no ACK). Written by the receive thread (one assignment each), read by the
        #: supervisor, which reports and acts.
        self.last_error: tuple[float, ErrorFrame] | None = None
        self.last_losing_error = 0.0
        self.receive_error: tuple[float, str] | None = None
        self.bits = 0
        self._window_start = time.monotonic()
        self._window_bits = 0
        self.load = 0.0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.error_frames += 1
            error = decode_error_frame(msg.arbitration_id, bytes(msg.data))
            now = time.monotonic()
            self.last_error = (now, error)
            if error.loses_the_bus:
                self.last_losing_error = now
            return
        self.frames += 1
        bits = frame_bits(min(msg.dlc, 8), extended=msg.is_extended_id)
        self.bits += bits
        self._window_bits += bits

    def on_error(self, exc: Exception) -> None:
        """The receive thread's error (python-can calls it; handled here, the thread does not die
        with a traceback): noted for the supervisor, which declares the bus lost (the notifier's
        ``exception``) and reconnects. A kernel socket reports ENETDOWN once when its interface
        goes down and receives again when it is up; the pause bounds a receive that keeps failing
        to RX_ERROR_PAUSE_S per try (no spinning thread)."""
        self.receive_error = (time.monotonic(), str(exc))
        logger.debug("receive error: %s", exc)
        time.sleep(RX_ERROR_PAUSE_S)

    def sample(self) -> float:
        """Bus load (0..1) seen since the last sample."""
        now = time.monotonic()
        elapsed = now - self._window_start
        if elapsed > 0:
            self.load = self._window_bits / (elapsed * self.bitrate)
        self._window_start, self._window_bits = now, 0
        return self.load


class ForeignTraffic(can.Listener):
    """Frames that only another master sends (this driver never receives its own): SYNC, NMT
    commands, heartbeats with the host's own node id, SDO writes to this driver's drives.
    The receive thread stores when it last saw each (one assignment each); the supervisor
    reads them and decides."""

    def __init__(self, host_node_id: int, node_ids: Collection[int]) -> None:
        self.host_node_id = host_node_id
        self.node_ids = frozenset(node_ids)
        self.sync = 0.0
        #: set while this driver's SYNC reaches this listener (the socketcand daemon's timer, or the
        #: kernel's broadcast manager, whose frames SocketCAN loops back to the host's other
        #: sockets): another master's SYNC then shows as more SYNC frames than that period gives
        self.own_sync_period_s = 0.0
        #: SocketCAN marks each frame made on this host (is_rx False): a SYNC with is_rx True
        #: came over the wire from another node, which only another master sends
        self.marks_local_frames = False
        self._syncs: deque[float] = deque()  # receive thread only
        self.sync_excess = (0, 0.0)  # (SYNC frames seen, own period gives) in the last window over the rate
        self.host_twin = 0.0
        self.nmt: dict[tuple[int, int], float] = {}  # (target node (0: all), command) -> when
        self.sdo: dict[int, float] = {}  # node -> when another client sent it an SDO request
        #: node -> when an RPDO to it passed: only another master's before this driver sends any
        #: (read by :meth:`master_evidence`, the look before the first NMT command)
        self.rpdo: dict[int, float] = {}

    def on_message_received(self, msg: can.Message) -> None:
        cob = msg.arbitration_id
        if msg.is_error_frame or msg.is_extended_id:
            return
        if cob == 0x080:
            now = time.monotonic()
            period = self.own_sync_period_s
            if period <= 0 or (self.marks_local_frames and msg.is_rx):
                self.sync = now
                return
            # counted by the bus's timestamps, not by arrival: a busy process reads a burst of them
            wire = msg.timestamp or time.time()
            syncs = self._syncs
            syncs.append(wire)
            while wire - syncs[0] > SYNC_RATE_WINDOW_S:
                syncs.popleft()
            if len(syncs) > 1.5 * SYNC_RATE_WINDOW_S / period + 2:
                self.sync = now
                self.sync_excess = (len(syncs), SYNC_RATE_WINDOW_S / period)
        elif cob == 0x000 and len(msg.data) == 2:
            self.nmt[msg.data[1], msg.data[0]] = time.monotonic()  # each command kept: a reset then a start
        elif cob == 0x700 + self.host_node_id:
            self.host_twin = time.monotonic()
        elif 0x601 <= cob <= 0x67F and cob - 0x600 in self.node_ids and msg.data and msg.data[0] & 0xE0 == 0x20:
            self.sdo[cob - 0x600] = time.monotonic()  # a download (write); reads by bench tools are harmless
        elif 0x200 <= cob < 0x580 and not cob & 0x80 and cob & 0x7F in self.node_ids:
            self.rpdo[cob & 0x7F] = time.monotonic()  # RPDO1-4 (0x200, 0x300, 0x400, 0x500 + node)

    def evidence(self, node_id: int, since: float) -> str:
        """What shows another master acting on ``node_id`` after ``since`` ('' when nothing)."""
        found = []
        if self.host_twin > since:
            found.append(f"heartbeats of node {self.host_node_id}, this driver's own id: a second driver?")
        if self.sync > since:
            count, own = self.sync_excess
            more = f" ({count} in {SYNC_RATE_WINDOW_S:g} s where its own give {own:.0f})" if count else ""
            found.append(f"SYNC frames this driver did not send{more}")  # or more of them than it sends
        seen = list(self.nmt.items())  # one copy (the receive thread may add a key meanwhile)
        for (target, command), when in sorted(seen, key=lambda item: item[1]):
            if target in (node_id, 0) and when > since:
                found.append(f"NMT command 0x{command:02X} to {'all nodes' if target == 0 else f'node {target}'}")
        if self.sdo.get(node_id, 0.0) > since:
            found.append(f"SDO writes to node {node_id} from another client")
        return "; ".join(found)


    def master_evidence(self, since: float) -> str:
        """What shows a live master on the bus after ``since``, for any of this driver's drives
        ('' when nothing): the look before a first NMT command, when none of it can be this
        driver's own."""
        found = [self.evidence(node, since) for node in sorted(self.node_ids)]
        found += [f"RPDOs to node {node}" for node, when in sorted(self.rpdo.items()) if when > since]
        unique = list(dict.fromkeys(part for text in found for part in text.split("; ") if part))
        return "; ".join(unique)


def look_for_master(bus: can.BusABC, host_node_id: int, node_ids: Collection[int], seconds: float) -> str:
    """Listen on ``bus`` for ``seconds`` before anything is sent to it; the evidence of another
    live master ('' when none): its heartbeat with the host id, SYNC, NMT commands, RPDOs or SDO
    writes to ``node_ids``. For a bus of its own (a bench command); the driver keeps a listener."""
    foreign = ForeignTraffic(host_node_id, node_ids)
    since = time.monotonic()
    deadline = since + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(remaining)
        if msg is not None:
            foreign.on_message_received(msg)
    return foreign.master_evidence(since - 1.0)


def other_master_error(where: str, evidence: str) -> ForeignMasterError:
    return ForeignMasterError(f"{where}: another master is live on the bus ({evidence}); nothing was sent. Two"
                              " masters on one drive fight over it: stop the other driver or tool first. To take"
                              " the bus over anyway (its drives are reset and disarmed): --force on the bench,"
                              " MotorDriver.start(take_over=True) in Python.", evidence=evidence)


def look_window_s(host_heartbeat_s: float) -> float:
    return max(LOOK_MIN_S, 2.0 * host_heartbeat_s)


def carries_remote_frames(bus: can.BusABC) -> bool:
    """Every python-can interface carries remote frames but socketcand (its rawmode has none)."""
    return not type(bus).__module__.startswith("can.interfaces.socketcand")


def is_kernel_bus(bus: can.BusABC) -> bool:
    """A python-can bus on a kernel SocketCAN interface (can0 on the Orin, vcan0 in CI)."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return False
    return isinstance(bus, SocketcanBus)


def sync_daemon(bus_cfg: BusConfig) -> tuple[str, int, str] | None:
    """(host, port, channel) of the socketcand daemon whose timer sends the bus's SYNC, or None
    (not socketcand, or ``sync_timer: thread`` in the config)."""
    kwargs = bus_cfg.bus_kwargs()
    if bus_cfg.interface != "socketcand" or bus_cfg.sync_timer != "auto":
        return None
    return str(kwargs.get("host", "127.0.0.1")), int(kwargs.get("port", 29536)), bus_cfg.channel


class BusHandle:
    """One bus with its canopen network and SYNC task."""

    def __init__(self, name: str, bus: can.BusABC, owned: bool, sync_period_s: float,
                 bitrate: int = 1_000_000, foreign: ForeignTraffic | None = None,
                 daemon: tuple[str, int, str] | None = None, recorder: FlightRecorder | None = None) -> None:
        self.name = name
        self.recorder = recorder
        self.daemon = daemon  # (host, port, channel): the socketcand daemon's timer sends the SYNC
        self.bus = bus
        self.owned = owned
        self.sync_period_s = sync_period_s
        self.stats = BusStats(bitrate)
        self.network = GuardedNetwork(bus)
        self.network.NOTIFIER_CYCLE = NOTIFIER_TIMEOUT_S
        self.foreign = foreign or ForeignTraffic(0, ())
        self.foreign.marks_local_frames = is_kernel_bus(bus)
        self.network.listeners += [self.stats, self.foreign]  # before connect(): its Notifier copies the list
        if recorder is not None:
            self.network.listeners.append(recorder.listener(name))
            self.network.on_sent = functools.partial(recorder.record_sent, name)
        self.network.connect()
        self.sync_task: can.broadcastmanager.CyclicSendTaskABC | DaemonCyclicTask | None = None
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"rovercan-{name}")
        self.job: Future[None] | None = None  # the bus's reconnect, while it runs
        self.host_beats = 0
        self.late_beats = 0
        self.last_beat = 0.0
        self.next_beat = 0.0
        self.backoff_s = RECONNECT_MIN_S
        self.next_attempt = 0.0
        self.last_frames = 0
        self.last_rx = 0.0
        #: supervisor's: the newest error frame it reported, and since when sends have failed
        #: (a host heartbeat that could not be sent: ENETDOWN, ENOBUFS) with the last error
        self.reported_error = 0.0
        self.reported_losing = 0.0
        self.send_failing: tuple[float, str] | None = None

    def disconnect(self) -> None:
        """Drop a lost bus: SYNC, receive thread and socket (the network object stays)."""
        self.stop_sync()
        notifier = self.network.notifier
        if notifier is not None:
            notifier.stop(timeout=1.0)
            self.network.notifier = None
        try:
            self.bus.shutdown()
        except (can.CanError, OSError):
            pass

    def reconnect(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.network.bus = bus
        self.network.notifier = can.Notifier(bus, self.network.listeners, NOTIFIER_TIMEOUT_S)

    def start_sync(self) -> None:
        """SYNC by the bus's own timer where there is one: the socketcand daemon's broadcast
        manager, or (python-can on SocketCAN) the kernel's; else python-can's thread."""
        if self.sync_task is None and self.sync_period_s > 0:
            msg = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
            if self.daemon is not None:
                host, port, channel = self.daemon
                self.foreign.own_sync_period_s = self.sync_period_s  # its SYNC reaches us: judge by rate
                try:
                    self.sync_task = DaemonCyclicTask(host, port, channel, msg, self.sync_period_s)
                    return
                except BusLostError as err:
                    logger.warning("bus %s: %s; SYNC from a thread of this process instead", self.name, err)
            # the kernel's BCM (python-can on SocketCAN) sends from a socket of its own, and the
            # kernel loops its frames back to this one: judged by their rate, from the first one
            # on (it can arrive before send_periodic returns); a thread sends through the
            # driver's own socket, which does not receive its own frames: any SYNC is another's
            self.foreign.own_sync_period_s = self.sync_period_s
            task = self.bus.send_periodic(msg, self.sync_period_s, store_task=False)
            self.sync_task = task
            if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask):
                self.foreign.own_sync_period_s = 0.0
                task.on_error = self._sync_failed

    def job_done(self) -> bool:
        return self.job is None or self.job.done()

    def restart_sync(self) -> None:
        """On the bus's worker: a SYNC job the daemon dropped is set up again."""
        self.stop_sync()
        self.start_sync()

    def _sync_failed(self, exc: Exception) -> bool:
        """The SYNC thread could not send (bus gone): stop it; the supervisor reconnects."""
        logger.error("bus %s: SYNC stopped: %s", self.name, exc)
        return False

    def stop_sync(self) -> None:
        if self.sync_task is not None:
            self.sync_task.stop()
            self.sync_task = None

    def beat(self, host_node_id: int) -> None:
        """One host heartbeat (NMT state operational), sent from the supervisor loop."""
        try:
            beat = can.Message(arbitration_id=0x700 + host_node_id, data=bytes([NmtState.OPERATIONAL]),
                               is_extended_id=False)
            self.bus.send(beat)
            self.host_beats += 1
            self.send_failing = None
            if self.recorder is not None:
                self.recorder.record_sent(self.name, beat)
        except (can.CanError, OSError, ValueError) as err:  # the supervisor decides when the bus is lost
            logger.debug("bus %s: host heartbeat not sent: %s", self.name, err)
            if self.send_failing is None:
                self.send_failing = (time.monotonic(), str(err))

    def close(self) -> None:
        self.stop_sync()
        self.worker.shutdown(wait=True, cancel_futures=True)
        notifier = self.network.notifier
        if notifier is not None:
            notifier.stop(timeout=1.0)
            self.network.notifier = None
        if self.owned:
            try:
                self.bus.shutdown()
            except (can.CanError, OSError):
                pass


class MotorDriver:
    """All drives of a :class:`RoverConfig`. A context manager; ``close()`` is idempotent.

    ``buses`` maps bus names to already-open python-can buses (tests, the emulator); any
    other configured bus is opened with ``can.Bus(**bus_config.bus_kwargs())``.
    """

    def __init__(self, config: RoverConfig, buses: Mapping[str, can.BusABC] | None = None, *,
                 force: bool = False) -> None:
        self.config = config
        for load in plan_load(config):  # refuse a config the bus cannot carry, before touching it
            if load.load > MAX_LOAD and not force:
                raise ConfigError(f"bus {load.bus!r}: the configured traffic needs {load.load:.0%} of"
                                  f" {load.bitrate} bit/s (worst case); lengthen sync_period_ms, raise the"
                                  " bitrate or move drives to another bus (rovercan plan shows the budget),"
                                  " or force it")
            if load.load > WARN_LOAD:
                logger.warning("bus %s: planned load %.0f%% of %d bit/s (worst case)", load.bus,
                               load.load * 100, load.bitrate)
        self._handles: dict[str, BusHandle] = {}
        self.drives: dict[str, Drive] = {}
        self._closed = False
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self.bus_lost: dict[str, bool] = {}
        self._reboots: dict[str, Future[None]] = {}  # drive name -> its re-boot on the bus worker
        given = dict(buses or {})
        self.recorder = FlightRecorder(config.recorder, {d.name: (d.bus, d.node_id) for d in config.drives},
                                       {b.name: b.channel for b in config.buses},
                                       config.source) if config.recorder.enabled else None
        self._host_loss_seen: dict[str, int] = {}  # supervisor: host-loss stops already reported
        self._take_over = False  # start(take_over=True): another master's traffic is not held against it
        # every EDS is loaded and checked before any hardware is touched
        ods = {d.name: load_drive_od(d.eds, d.node_id) for d in config.drives}
        try:
            for bus_cfg in config.buses:
                bus = given.get(bus_cfg.name)
                owned = bus is None
                if bus is None:
                    try:
                        bus = open_bus(bus_cfg.bus_kwargs(), bus_cfg.connect_timeout_s)
                    except BusLostError:
                        raise
                    except (can.CanError, OSError, ValueError, ImportError) as err:
                        raise BusLostError(f"bus {bus_cfg.name!r}: cannot open {bus_cfg.bus_kwargs()}:"
                                           f" {err}. Is the interface up (ip link) or the simulator"
                                           " running (rovercan sim)?") from err
                foreign = ForeignTraffic(bus_cfg.host_node_id, [d.node_id for d in config.drives if d.bus == bus_cfg.name])
                self._handles[bus_cfg.name] = BusHandle(bus_cfg.name, bus, owned, bus_cfg.sync_period_s,
                                                        bus_cfg.bitrate, foreign, sync_daemon(bus_cfg),
                                                        self.recorder)
                self.bus_lost[bus_cfg.name] = False
            for drive_cfg in config.drives:
                bus_cfg = config.bus(drive_cfg.bus)
                self.drives[drive_cfg.name] = Drive(drive_cfg, self._handles[drive_cfg.bus].network,
                                                    ods[drive_cfg.name], host_node_id=bus_cfg.host_node_id,
                                                    sync_period_s=bus_cfg.sync_period_s)
                self.drives[drive_cfg.name].remote_frames = carries_remote_frames(self._handles[drive_cfg.bus].bus)
        except BaseException:
            self._close_buses()
            if self.recorder is not None:
                self.recorder.close()
            raise

    # ------------------------------------------------------------------ lifecycle
    def start(self, *, reset: bool = True, take_over: bool = False) -> MotorDriver:
        """Look for another master, boot every drive (buses in parallel), start SYNC and
        supervision; enable only drives configured with ``arm_on_start``.

        Before its first NMT command the driver listens two host-heartbeat periods (at least
        LOOK_MIN_S) on each bus: another live master (a heartbeat with this driver's host id,
        SYNC, NMT commands, RPDOs or SDO writes to its drives) makes it refuse with
        :class:`ForeignMasterError`, nothing sent, unless ``take_over``."""
        self._take_over = take_over
        try:
            self._look(take_over)
            self._start(reset)
        except BaseException:  # a failed or interrupted start leaves nothing armed or open
            self.close()
            raise
        return self

    def _look(self, take_over: bool) -> None:
        window = max(look_window_s(b.host_heartbeat_s) for b in self.config.buses)
        since = time.monotonic()
        time.sleep(window)
        for name, handle in self._handles.items():
            evidence = handle.foreign.master_evidence(since - 1.0)
            if not evidence:
                continue
            if not take_over:
                raise other_master_error(f"bus {name}", evidence)
            logger.warning("bus %s: another master is live (%s); taking the bus over as told", name, evidence)

    def _start(self, reset: bool) -> None:
        with ThreadPoolExecutor(max_workers=max(1, len(self.drives)),
                                thread_name_prefix="rovercan-boot") as pool:
            futures = [pool.submit(d.boot, reset=reset) for d in self.drives.values()]
            for future in futures:
                future.result()
        for handle in self._handles.values():
            handle.start_sync()
            handle.worker.submit(lambda: None).result()  # its thread now, not at the first bus loss
        self._supervisor = threading.Thread(target=self._supervise, daemon=True,
                                            name="rovercan-supervisor")
        self._supervisor.start()
        for drive in self.drives.values():
            if drive.config.arm_on_start:
                drive.enable()

    def __enter__(self) -> MotorDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def drive(self, name: str) -> Drive:
        try:
            return self.drives[name]
        except KeyError:
            raise ConfigError(f"unknown joint {name!r}; configured joints: {sorted(self.drives)}") from None

    def __iter__(self) -> Iterator[Drive]:
        return iter(self.drives.values())

    def states(self) -> list[DriveState]:
        return [d.snapshot() for d in self.drives.values()]

    @property
    def buses(self) -> dict[str, BusHandle]:
        return dict(self._handles)

    # ------------------------------------------------------------------ supervision
    def _supervise(self) -> None:
        while not self._stop.wait(SUPERVISOR_PERIOD_S):
            now = time.monotonic()
            self._beat(now)
            if self.recorder is not None and self.recorder.wants_sample():
                self.recorder.sample([d.snapshot() for d in self.drives.values()])
            for drive in self.drives.values():
                try:
                    self._supervise_drive(drive, now)
                except MotorError as err:
                    logger.error("supervisor: %s", err)
                except Exception:
                    logger.exception("supervisor: unexpected error on %s", drive.name)
            for name, handle in self._handles.items():
                try:
                    self._supervise_bus(name, handle, now)
                except Exception:
                    logger.exception("supervisor: unexpected error on bus %s", name)

    def _check_foreign(self, drive: Drive, now: float) -> None:
        """Another master on the drive's bus (within FOREIGN_HOLD_S): mark it; once it has been
        quiet for FOREIGN_RELEASE_S, clear the mark (the drive is then configured again)."""
        if self._take_over:
            return  # told to take the bus over: the other master's traffic is expected
        foreign = self._handles[drive.config.bus].foreign
        evidence = foreign.evidence(drive.node_id, now - FOREIGN_HOLD_S)
        when, what = drive.behind_back
        if when > now - FOREIGN_HOLD_S:
            evidence = "; ".join(filter(None, (evidence, what)))
        if evidence:
            if drive.set_foreign_master(evidence):  # an SDO blocks: on the bus's worker
                self._handles[drive.config.bus].worker.submit(drive.quick_stop_by_sdo, now)
        elif drive.foreign_master and not foreign.evidence(drive.node_id, now - FOREIGN_RELEASE_S) \
                and drive.behind_back[0] <= now - FOREIGN_RELEASE_S:
            drive.set_foreign_master("")

    def _beat(self, now: float) -> None:
        """The host heartbeat on every bus that is up, from this loop: when the loop stops (the
        process killed, hung, stopped), the heartbeat stops and the drives stop themselves."""
        for name, handle in self._handles.items():
            if now >= handle.next_beat and not self.bus_lost[name]:
                bus_cfg = self.config.bus(name)
                handle.beat(bus_cfg.host_node_id)
                if handle.last_beat and now - handle.last_beat > 2 * bus_cfg.host_heartbeat_s:
                    handle.late_beats += 1
                    logger.warning("bus %s: host heartbeat %.0f ms late (period %.0f ms): this process is starved;"
                                   " the drives stop by themselves when it is later than their host timeout",
                                   name, (now - handle.last_beat - bus_cfg.host_heartbeat_s) * 1000,
                                   bus_cfg.host_heartbeat_s * 1000)
                handle.last_beat = now
                handle.next_beat = max(handle.next_beat + bus_cfg.host_heartbeat_s, now)

    def _supervise_bus(self, name: str, handle: BusHandle, now: float) -> None:
        """A bus is lost when its receive thread failed, or when every drive on it lost its
        heartbeat and nothing at all arrived for a consumer time (a socketcand server that died,
        an unplugged adapter). A bus the driver opened itself is then reconnected with back-off
        on the bus's worker and its drives are booted again (not re-armed: commands are refused
        until someone enables them)."""
        bus_cfg = self.config.bus(name)
        if not self.bus_lost[name]:
            sync = handle.sync_task
            if isinstance(sync, DaemonCyclicTask) and not sync.keep_alive(now) and handle.job_done():
                handle.job = handle.worker.submit(handle.restart_sync)  # the daemon dropped the SYNC job
            exc = handle.network.notifier.exception if handle.network.notifier else None
            drives = [d for d in self.drives.values() if d.config.bus == name]
            if handle.stats.frames != handle.last_frames:
                handle.last_frames, handle.last_rx = handle.stats.frames, now
            silent_for = now - handle.last_rx if handle.last_rx else 0.0
            timeout = max((d.config.heartbeat_timeout_s for d in drives), default=1.0)
            closed = connection_closed(handle.bus)
            losing = self._bus_error(name, handle)
            failing = handle.send_failing
            send_failed = failing is not None and now - failing[0] > SEND_FAILING_BEATS * bus_cfg.host_heartbeat_s
            if exc is not None or closed or losing or send_failed or (
                    drives and all(d.lost for d in drives) and silent_for > timeout):
                for drive in drives:  # first: no command passes once the bus counts as lost
                    drive.mark_lost()
                self.bus_lost[name] = True
                why = (f"receive failed: {exc}" if exc is not None else "the server closed the connection"
                       if closed else f"error frame: {losing}" if losing else
                       f"sends fail: {failing[1]}" if send_failed and failing else
                       f"nothing received for {silent_for:.1f} s")
                handle.send_failing = None
                logger.error("bus %s lost (%s)", name, why)
                if self.recorder is not None:
                    self.recorder.trigger("bus_lost", name, text=why)
                handle.last_beat = 0.0  # no heartbeat while the bus is gone: that is not lateness
                if handle.owned:  # reconnected on the bus's worker: joining a notifier can take a second
                    handle.next_attempt = float("inf")  # until the job says when to try again
                    handle.job = handle.worker.submit(self._reconnect, name, handle, True)
            return
        if not handle.owned or now < handle.next_attempt or (handle.job is not None and not handle.job.done()):
            return
        handle.next_attempt = float("inf")
        handle.job = handle.worker.submit(self._reconnect, name, handle)

    def _bus_error(self, name: str, handle: BusHandle) -> str:
        """Report the newest error frame that came since the last look (log, flight recorder; the
        count is in /diagnostics); return what it says when one since then loses the bus (bus-off,
        no ACK: the driver's frames reach no drive), else ''."""
        stats = handle.stats
        last = stats.last_error
        if last is None or last[0] <= handle.reported_error:
            return ""
        handle.reported_error = last[0]
        losing = stats.last_losing_error > handle.reported_losing
        handle.reported_losing = stats.last_losing_error
        logger.log(logging.ERROR if losing else logging.WARNING, "bus %s: error frame: %s (%d so far)", name,
                   last[1].text, stats.error_frames)
        if self.recorder is not None:
            self.recorder.trigger("bus_error", name, code=last[1].classes, text=last[1].text)
        return last[1].text if losing else ""

    def _reconnect(self, name: str, handle: BusHandle, drop: bool = False) -> None:
        """On the bus's worker: drop the lost connection (``drop``), open the bus again and boot
        its drives; back off on failure."""
        if drop:
            handle.disconnect()
        bus_cfg = self.config.bus(name)
        try:
            handle.reconnect(open_bus(bus_cfg.bus_kwargs(), connect_timeout_s=0.0))  # one try: the back-off is ours
        except (can.CanError, OSError, ValueError, TimeoutError, BusLostError) as err:
            handle.backoff_s = min(handle.backoff_s * 2, RECONNECT_MAX_S)
            handle.next_attempt = time.monotonic() + handle.backoff_s
            logger.warning("bus %s: reconnect failed (%s); next try in %.1f s", name, err, handle.backoff_s)
            return
        handle.backoff_s = RECONNECT_MIN_S
        try:
            for drive in (d for d in self.drives.values() if d.config.bus == name):
                drive.boot(reset=True)
        except BusLostError as err:  # opened, but nothing goes out (an interface still down)
            handle.disconnect()
            handle.backoff_s = min(handle.backoff_s * 2, RECONNECT_MAX_S)
            handle.next_attempt = time.monotonic() + handle.backoff_s
            logger.warning("bus %s: still not usable (%s); next try in %.1f s", name, err, handle.backoff_s)
            return
        except MotorError as err:
            logger.error("bus %s is back but a drive did not boot: %s; retrying", name, err)
            handle.disconnect()
            handle.next_attempt = time.monotonic() + handle.backoff_s
            return
        handle.start_sync()
        self.bus_lost[name] = False
        logger.warning("bus %s re-established; drives configured again (not enabled)", name)

    def _supervise_drive(self, drive: Drive, now: float) -> None:
        cfg = drive.config
        self._check_foreign(drive, now)
        if drive.foreign_master:
            return  # nothing of ours goes to a drive another master drives (no re-boot, no watchdog)
        if drive.rebooted.is_set():
            job = self._reboots.get(drive.name)
            if (job is None or job.done()) and not self.bus_lost[cfg.bus]:
                self._reboots[drive.name] = self._handles[cfg.bus].worker.submit(drive.reconfigure)
            return
        was_lost = drive.lost
        drive.guard(now)
        drive.check_heartbeat(now)
        if drive.lost and not was_lost:
            self._incident("heartbeat_lost", drive, "heartbeat lost")
        if drive.host_loss_stops != self._host_loss_seen.get(drive.name, 0):
            self._host_loss_seen[drive.name] = drive.host_loss_stops
            self._incident("host_loss_stop", drive, "the drive had stopped itself: the host was gone (0x8130)")
        if drive.velocity_commanded and now - drive.last_velocity_cmd > cfg.watchdog_s:
            logger.warning("%s: no velocity command for %.0f ms (watchdog %.0f ms); stopping",
                           drive.name, (now - drive.last_velocity_cmd) * 1000, cfg.watchdog_s * 1000)
            if drive.stop_velocity():
                self._incident("watchdog_stop", drive, f"no command for {cfg.watchdog_s * 1000:.0f} ms")
        drive.guard_limits()

    def _incident(self, kind: str, drive: Drive, text: str) -> None:
        if self.recorder is not None:
            self.recorder.trigger(kind, drive.config.bus, node=drive.node_id, drive=drive.name, text=text)

    # ------------------------------------------------------------------ shutdown
    def safe_stop(self) -> None:
        """Quick-stop and disable every drive that is powered (errors are collected, not lost)."""
        errors: list[str] = []
        for drive in self.drives.values():
            if drive.lost or not drive.booted:
                continue
            try:
                if drive.state == State.OPERATION_ENABLED:
                    drive.quick_stop()
                drive.disable_voltage()
            except MotorError as err:
                errors.append(str(err))
        for message in errors:
            logger.error("safe stop: %s", message)

    def close(self) -> None:
        """Quick stop + disable drives, stop SYNC, stop threads, close buses. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for drive in self.drives.values():
            drive.closed = True  # refuse new commands from here on; safe_stop bypasses the check
        try:
            self.safe_stop()  # the host heartbeat goes on meanwhile: no drive reacts to its loss yet
        finally:
            self._stop.set()
            if self._supervisor is not None and self._supervisor is not threading.current_thread():
                self._supervisor.join(timeout=2.0)
            for handle in self._handles.values():
                handle.worker.shutdown(wait=True, cancel_futures=True)  # a re-boot under way ends first
            self._release_host_watch()
            self._close_buses()
            if self.recorder is not None:
                self.recorder.close()  # writes what is pending

    def _release_host_watch(self) -> None:
        for drive in self.drives.values():
            try:
                drive.release_host_watch()
            except MotorError as err:
                logger.info("%s: host watch left armed (%s); the drive reports the host's silence", drive.name, err)

    def _close_buses(self) -> None:
        for handle in self._handles.values():
            handle.stop_sync()
        for handle in self._handles.values():
            handle.close()

"""One bus of the driver: the python-can bus, its canopen network, the SYNC producer and the
worker thread for the bus's blocking jobs.

Owners: the connection (``bus``, the network's notifier, ``sync_task``) is set up by the
driver's constructor and ``start`` before any thread runs, and from then on changed only by jobs
on the bus's worker (reconnect, SYNC restart), one at a time; the supervisor thread sends the
host heartbeat through it (:meth:`BusHandle.beat`, which counts ``host_beats``). The supervisor's
bookkeeping of the bus (lost, back-off, lateness) is its own :class:`motor_driver.drive.ledger.BusRecord`.

The bus's receive thread (python-can's Notifier) runs as every other thread of the driver's
process does: under SCHED_FIFO where the node made it real-time (nodes/process/spinning.go_realtime). Run
ordinary, it would take a SYNC period's frames in fewer wake-ups (0.026 of a core less with the
rover's config), but it holds the interpreter while it decodes a frame, and an ordinary thread
holding it is preempted there by any real-time or favoured work on its core: every other thread
of the driver (the commands, the host heartbeat) then waits for the interpreter. With twelve
drives on three buses beside real-time load that stood the command thread still for 5-31 ms at a
time, lost 5-14 % of a 500 Hz arm's set-points and let the host heartbeat's gaps grow until every
drive stopped itself; real-time, none is lost, at the same CPU (docs/performance.md).
The echo of the daemon's SYNC does not wake it alone (adapters.hold_lone_sync, while the job runs).
"""

from __future__ import annotations

import functools
import logging
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

import can

from can_config.bits import frame_bits
from can_config.config import BusConfig
from can_config.errors import BusLostError
from can_config.model import SOCKETCAND_PORT
from can_config.objects import FunctionCode, NmtState
from motor_driver.bus.adapters import (
    FRAME_ERROR,
    Frame,
    GuardedNetwork,
    dispatch_batches,
    hold_lone_sync,
    queue_full,
    room_to_send,
    stall_of,
    watch_idle,
)
from motor_driver.bus.connect import is_kernel_bus
from motor_driver.bus.cyclic import DaemonCyclicTask
from motor_driver.bus.traffic import BusStats, ForeignTraffic
from motor_driver.process.jobs import brief_error

logger = logging.getLogger(__name__)

NOTIFIER_TIMEOUT_S = 0.1
#: Host heartbeats that could not be sent in a row (their periods) before the bus counts as lost.
SEND_FAILING_BEATS = 3
#: The longest the host heartbeat waits for the bus's send lock. A frame's write holds it for tens
#: of microseconds; longer is a write blocked (at most SEND_STALL_S, adapters) or its thread
#: starved: the beat is then skipped, tried again next period, and the supervisor's loop (every
#: bus's heartbeat) never waits behind one bus's writer.
BEAT_LOCK_S = 0.01
#: What :meth:`BusHandle.beat` says when it skipped for the lock (nothing was tried on the bus).
BEAT_LOCK_BUSY = f"the bus's send lock stayed held over {BEAT_LOCK_S * 1000:.0f} ms (a write blocked, or its thread starved)"
RECONNECT_MIN_S = 0.2
RECONNECT_MAX_S = 5.0


def sync_daemon(bus_cfg: BusConfig) -> tuple[str, int, str] | None:
    """(host, port, channel) of the socketcand daemon whose timer sends the bus's SYNC, or None
    (not socketcand, or ``sync_timer: thread`` in the config)."""
    kwargs = bus_cfg.bus_kwargs()
    if bus_cfg.interface != "socketcand" or bus_cfg.sync_timer != "auto":
        return None
    return str(kwargs.get("host", "127.0.0.1")), int(kwargs.get("port", SOCKETCAND_PORT)), bus_cfg.channel


class FrameTap(Protocol):
    """The flight recorder's receive tap of one bus: a frame as python-can hands it, or the frames
    of one batch read (:data:`motor_driver.bus.adapters.Frame`, no ``can.Message``), together."""

    def on_message_received(self, msg: can.Message) -> None: ...

    def on_read(self, frames: Sequence[Frame]) -> None: ...


class FrameRecorder(Protocol):
    """What a bus hands the flight recorder (:class:`motor_driver.recording.flight.FlightRecorder`
    is one; the bus, a layer below, does not import it): every frame heard and every frame sent."""

    def listener(self, bus: str) -> FrameTap: ...

    def record_sent(self, bus: str, msg: can.Message) -> None: ...

    def record_frame(self, bus: str, can_id: int, data: bytes | bytearray, remote: bool = False) -> None: ...


#: worst-case bits of an 11-bit data frame by its length (a longer one, which socketcand's text can
#: carry, counted as 8 bytes as BusStats counts it)
_STD_BITS = tuple(frame_bits(min(n, 8)) for n in range(9))
_EXT_BITS = tuple(frame_bits(min(n, 8), extended=True) for n in range(9))


class FrameDispatch(can.Listener):  # type: ignore[misc]
    """The one listener of the bus's receive thread: each frame dispatched to the drives'
    callbacks (an 11-bit data frame: canopen would dispatch an extended one by its low bits),
    counted, looked at for another master and handed to the flight recorder, in that order, in
    one call. python-can's Notifier called five listeners a frame, each through
    ``Listener.__call__``, and the dispatch went through canopen's listener and an 11-bit filter in
    front of it (docs/performance.md: a third of the receive thread's own time). A receive error
    is the counters' (:meth:`BusStats.on_error`: noted for the supervisor, paused).

    On socketcand a read's frames come in one call (:meth:`on_frames`, through
    :func:`~motor_driver.bus.adapters.dispatch_batches`): the same work in the same order without
    a ``can.Message``, a Notifier round and four calls per frame; the counters are added once a read."""

    def __init__(self, network: GuardedNetwork, stats: BusStats, foreign: ForeignTraffic,
                 tap: FrameTap | None = None) -> None:
        self._notify, self._stats, self._foreign = network.notify, stats.on_message_received, foreign.on_message_received
        self._counters, self._foreign_frame = stats, foreign.on_frame
        self._tap = tap.on_message_received if tap is not None else None
        self._tap_read = tap.on_read if tap is not None else None
        self._on_error = stats.on_error

    def on_message_received(self, msg: can.Message) -> None:
        if not (msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame):
            self._notify(msg.arbitration_id, msg.data, msg.timestamp)
        self._stats(msg)
        self._foreign(msg)
        if (tap := self._tap) is not None:
            tap(msg)

    def on_frames(self, frames: deque[Frame]) -> None:
        """The frames of one read, taken in order (what a raise leaves stays in ``frames``): as
        :meth:`on_message_received` does each. A TPDO (0x181-0x4FF, bit 7 set) is no other
        master's evidence and skips that look. The recorder gets the frames taken at the end, together
        (one take of its ring's lock a read)."""
        notify, foreign, tap, stats = self._notify, self._foreign_frame, self._tap_read, self._counters
        count = syncs = bits = 0
        taken: list[Frame] = []
        keep = taken.append
        try:
            while frames:
                frame = frames.popleft()
                keep(frame)
                can_id, data, stamp, flags = frame
                size = len(data)
                if not flags:
                    count += 1
                    bits += _STD_BITS[size if size < 8 else 8]
                    notify(can_id, data, stamp)
                    if can_id == 0x080:
                        syncs += 1
                        foreign(can_id, data, stamp)
                    elif not (can_id & 0x80 and 0x180 <= can_id < 0x500):
                        foreign(can_id, data, stamp)
                elif flags & FRAME_ERROR:
                    stats.on_error_frame(can_id, data)
                else:
                    count += 1
                    bits += _EXT_BITS[size if size < 8 else 8]
        finally:
            if taken:
                stats.count(count, syncs, bits, taken[-1][2])
                if tap is not None:
                    tap(taken)

    def on_error(self, exc: Exception) -> None:
        logger.debug("receive failed: %s", brief_error(exc))
        self._on_error(exc)

    def stop(self, *args: object) -> None:
        pass


def receive_from(bus: can.BusABC, sink: Callable[[deque[Frame]], None], on_idle: Callable[[float], None]) -> None:
    """How the bus's receive thread reads: a socketcand read's frames at once to ``sink``, elsewhere
    python-can's ``recv`` (a frame at a time to the listener); either way ``on_idle`` is told of
    every wait that came back with nothing (:attr:`BusStats.idle_at`)."""
    if not dispatch_batches(bus, sink, on_idle):
        watch_idle(bus, on_idle)


class BusHandle:
    """One bus with its canopen network and SYNC task."""

    def __init__(self, name: str, bus: can.BusABC, owned: bool, sync_period_s: float,
                 bitrate: int = 1_000_000, foreign: ForeignTraffic | None = None,
                 daemon: tuple[str, int, str] | None = None, recorder: FrameRecorder | None = None) -> None:
        self.name = name
        self.recorder = recorder
        self.daemon_address = daemon  # (host, port, channel): the socketcand daemon's timer sends the SYNC
        self.bus = bus
        self.owned = owned
        self.sync_period_s = sync_period_s
        self.stats = BusStats(bitrate)
        self.foreign = foreign or ForeignTraffic(0, ())
        self.foreign.set_marks_local_frames(is_kernel_bus(bus))
        self.network = GuardedNetwork(bus, (), functools.partial(recorder.record_frame, name)
                                      if recorder is not None else None)
        # one listener does it all (its on_error keeps a receive error quiet: the supervisor says the loss);
        # on socketcand it takes each read's frames at once
        self.dispatch = FrameDispatch(self.network, self.stats, self.foreign,
                                      recorder.listener(name) if recorder is not None else None)
        self.network.listen_with(self.dispatch)
        receive_from(bus, self.dispatch.on_frames, self.stats.on_idle)
        self.network.NOTIFIER_CYCLE = NOTIFIER_TIMEOUT_S
        self.network.connect()  # its receive thread takes this thread's scheduling: module docstring
        self.sync_task: can.broadcastmanager.CyclicSendTaskABC | DaemonCyclicTask | None = None
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"rovercan-{name}")
        self.host_beats = 0  # the supervisor thread's (beat)

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
        receive_from(bus, self.dispatch.on_frames, self.stats.on_idle)
        # the new receive thread takes this thread's scheduling (the bus's worker: the process's)
        self.network.notifier = can.Notifier(bus, self.network.listeners, NOTIFIER_TIMEOUT_S)

    def start_sync(self) -> None:
        """SYNC by the bus's own timer where there is one: the socketcand daemon's broadcast
        manager, or (python-can on SocketCAN) the kernel's; else python-can's thread."""
        if self.sync_task is None and self.sync_period_s > 0:
            msg = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
            if self.daemon_address is not None:
                host, port, channel = self.daemon_address
                self.foreign.set_own_sync(self.sync_period_s)  # its SYNC reaches us: judge by rate
                try:
                    self.sync_task = DaemonCyclicTask(host, port, channel, msg, self.sync_period_s)
                    hold_lone_sync(self.bus, True)  # its echo alone does not wake the receive thread
                    return
                except BusLostError as err:
                    logger.warning("bus %s: %s; SYNC from a thread of this process instead", self.name, err)
            # the kernel's BCM (python-can on SocketCAN) sends from a socket of its own, and the
            # kernel loops its frames back to this one: judged by their rate, from the first one
            # on (it can arrive before send_periodic returns); a thread sends through the
            # driver's own socket, which does not receive its own frames: any SYNC is another's
            self.foreign.set_own_sync(self.sync_period_s)
            # not started yet: python-can's thread-based task must have its on_error before its
            # thread runs (a server that died during start-up raised in that thread, unhandled)
            task = self.bus.send_periodic(msg, self.sync_period_s, store_task=False, autostart=False)
            self.sync_task = task
            if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask):
                self.foreign.set_own_sync(0.0)
                task.on_error = self._sync_failed
                # its sends take the network's lock, as every other writer of this socket does (a
                # lock of its own let a SYNC's text interleave with an RPDO's on a TCP bus)
                task.send_lock = self.network.send_lock
            if isinstance(task, can.broadcastmanager.RestartableCyclicTaskABC):
                task.start()

    def restart_sync(self) -> None:
        """On the bus's worker: a SYNC job the daemon dropped is set up again."""
        self.stop_sync()
        self.start_sync()

    def _sync_failed(self, exc: Exception) -> bool:
        """The SYNC thread could not send (bus gone, or its write blocked: :func:`stall_of`): stop it;
        the supervisor says the loss and reconnects."""
        logger.info("bus %s: SYNC stopped: %s", self.name, stall_of(self.bus, exc) or brief_error(exc))
        return False

    def stop_sync(self) -> None:
        if self.sync_task is not None:
            self.sync_task.stop()
            self.sync_task = None
            hold_lone_sync(self.bus, False)  # no SYNC comes to push a frame without data through

    def beat(self, host_node_id: int) -> str | None:
        """One host heartbeat (NMT state operational), sent from the supervisor loop; why it could
        not be sent, or None. It never waits on this bus: the send lock is waited for at most
        BEAT_LOCK_S, and a socket that would block (the server not reading) is not written."""
        lock = self.network.send_lock  # one writer of the socket at a time (RPDOs, SDO, SYNC)
        try:
            beat = can.Message(arbitration_id=FunctionCode.HEARTBEAT + host_node_id, data=bytes([NmtState.OPERATIONAL]),
                               is_extended_id=False)
            if not lock.acquire(timeout=BEAT_LOCK_S):
                return stall_of(self.bus) or BEAT_LOCK_BUSY
            try:
                stalled = stall_of(self.bus)
                if stalled or not room_to_send(self.bus):
                    return stalled or "the server is not reading (the connection's buffer is full); heartbeat not sent"
                self.bus.send(beat)
            finally:
                lock.release()
            self.host_beats += 1
            if self.recorder is not None:
                self.recorder.record_sent(self.name, beat)
        except (can.CanError, OSError, ValueError) as err:  # the supervisor decides when the bus is lost
            logger.debug("bus %s: host heartbeat not sent: %s", self.name, err)
            if queue_full(err):  # counted with the network's (not retried: this loop never waits)
                self.network.count_queue_full()
            return stall_of(self.bus, err) or brief_error(err)
        return None

    def beats_sent(self) -> int:
        return self.host_beats

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

"""One bus of the driver: the python-can bus, its canopen network, the SYNC producer and the
worker thread for the bus's blocking jobs.

Owner: the supervisor thread (reconnect bookkeeping, the host heartbeat's send); the worker
runs the blocking jobs handed to it (re-boots, reconnects), one at a time.

The bus's receive thread (python-can's Notifier) runs under ordinary scheduling, also in a driver
whose other threads are SCHED_FIFO (nodes/runtime.go_realtime): real-time, it woke at once for
each arrival, about three times a SYNC period per bus (the SYNC's echo, then the TPDOs as they
came), at up to 0.1 ms of CPU a wake-up; ordinary, it takes what has come when it gets a core.
The echo of the daemon's SYNC does not wake it alone (adapters.hold_lone_sync, while the job runs).
The commands, the host heartbeat, the stops and DDS stay real-time (docs/performance.md).
"""

from __future__ import annotations

import functools
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor

import can

from can_config.config import BusConfig
from can_config.errors import BusLostError
from can_config.model import SOCKETCAND_PORT
from can_config.objects import FunctionCode, NmtState
from can_config.realtime import ordinary_thread
from motor_driver.adapters import GuardedNetwork, hold_lone_sync, queue_full
from motor_driver.connect import is_kernel_bus
from motor_driver.cyclic import DaemonCyclicTask
from motor_driver.recorder import FlightRecorder
from motor_driver.traffic import BusStats, ForeignTraffic

logger = logging.getLogger(__name__)

NOTIFIER_TIMEOUT_S = 0.1
#: Host heartbeats that could not be sent in a row (their periods) before the bus counts as lost.
SEND_FAILING_BEATS = 3
RECONNECT_MIN_S = 0.2
RECONNECT_MAX_S = 5.0


def sync_daemon(bus_cfg: BusConfig) -> tuple[str, int, str] | None:
    """(host, port, channel) of the socketcand daemon whose timer sends the bus's SYNC, or None
    (not socketcand, or ``sync_timer: thread`` in the config)."""
    kwargs = bus_cfg.bus_kwargs()
    if bus_cfg.interface != "socketcand" or bus_cfg.sync_timer != "auto":
        return None
    return str(kwargs.get("host", "127.0.0.1")), int(kwargs.get("port", SOCKETCAND_PORT)), bus_cfg.channel


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
            self.network.on_sent = functools.partial(recorder.record_frame, name)
        with ordinary_thread():  # the receive thread starts ordinary: module docstring
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
        self.reported_queue_full = 0  # supervisor's: ENOBUFS refusals already said
        self.link_down_said = False  # supervisor's: a kernel link's going down said, until it is back

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
        with ordinary_thread():  # the receive thread starts ordinary: module docstring
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
                    hold_lone_sync(self.bus, True)  # its echo alone does not wake the receive thread
                    return
                except BusLostError as err:
                    logger.warning("bus %s: %s; SYNC from a thread of this process instead", self.name, err)
            # the kernel's BCM (python-can on SocketCAN) sends from a socket of its own, and the
            # kernel loops its frames back to this one: judged by their rate, from the first one
            # on (it can arrive before send_periodic returns); a thread sends through the
            # driver's own socket, which does not receive its own frames: any SYNC is another's
            self.foreign.own_sync_period_s = self.sync_period_s
            # not started yet: python-can's thread-based task must have its on_error before its
            # thread runs (a server that died during start-up raised in that thread, unhandled)
            task = self.bus.send_periodic(msg, self.sync_period_s, store_task=False, autostart=False)
            self.sync_task = task
            if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask):
                self.foreign.own_sync_period_s = 0.0
                task.on_error = self._sync_failed
            if isinstance(task, can.broadcastmanager.RestartableCyclicTaskABC):
                task.start()

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
            hold_lone_sync(self.bus, False)  # no SYNC comes to push a frame without data through

    def beat(self, host_node_id: int) -> None:
        """One host heartbeat (NMT state operational), sent from the supervisor loop."""
        try:
            beat = can.Message(arbitration_id=FunctionCode.HEARTBEAT + host_node_id, data=bytes([NmtState.OPERATIONAL]),
                               is_extended_id=False)
            self.bus.send(beat)
            self.host_beats += 1
            self.send_failing = None
            if self.recorder is not None:
                self.recorder.record_sent(self.name, beat)
        except (can.CanError, OSError, ValueError) as err:  # the supervisor decides when the bus is lost
            logger.debug("bus %s: host heartbeat not sent: %s", self.name, err)
            if queue_full(err):  # counted with the network's (not retried: this loop never waits)
                self.network.tx_queue_full += 1
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

"""The supervisor thread (``rovercan-supervisor``), period SUPERVISOR_PERIOD_S, never blocks:
the host heartbeat on every bus, the drives' heartbeats, the velocity watchdog and the limit
guard, another master, every period; lost buses every BUS_CHECK_PERIODS; re-boots and
reconnects are handed to the bus's worker.

Owner: this thread owns ``bus_lost``, ``_host_loss_seen`` and each BusHandle's reconnect
bookkeeping; it changes a drive only through its methods, none of which waits.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from concurrent.futures import Future

import can

from can_config import RoverConfig
from can_config.errors import BusLostError, ConfigError, MotorError
from can_config.ratelimit import RateLimitedLog
from motor_driver.adapters import connection_closed
from motor_driver.bushandle import RECONNECT_MAX_S, RECONNECT_MIN_S, SEND_FAILING_BEATS, BusHandle
from motor_driver.bushealth import KernelBusHealth, read_kernel_health
from motor_driver.connect import open_bus
from motor_driver.cyclic import DaemonCyclicTask
from motor_driver.drive import Drive
from motor_driver.recorder import FlightRecorder
from motor_driver.traffic import FOREIGN_HOLD_S, FOREIGN_RELEASE_S

logger = logging.getLogger(__name__)

SUPERVISOR_PERIOD_S = 0.01
#: A bus is looked at (its connection, error frames, the SYNC job, silence) every this many
#: periods: a bus that goes is marked lost within 50 ms, inside the drives' own 150 ms host
#: timeout, which is what stops them; every period it was half the supervisor's CPU (a socket
#: peek and a select per bus, issue 43). Drives are looked at every period.
BUS_CHECK_PERIODS = 5


def supervisor_log() -> RateLimitedLog:
    """The supervisor's repeated warnings (a late heartbeat, each pass of a starved process), rate
    limited with a count."""
    return RateLimitedLog(logger)


class Supervision:
    """The supervisor thread's work for :class:`MotorDriver` (its base): one period of heartbeats,
    drives and buses, never blocking; re-boots and reconnects handed to each bus's worker."""

    config: RoverConfig
    drives: dict[str, Drive]
    recorder: FlightRecorder | None
    bus_lost: dict[str, bool]
    _handles: dict[str, BusHandle]
    _stop: threading.Event
    _closed: bool
    _take_over: bool
    _reboots: dict[str, Future[None]]
    _host_loss_seen: dict[str, int]
    _rate_limited: RateLimitedLog  # repeated warnings of this module (supervisor_log())

    def kernel_health(self, bus: str) -> tuple[KernelBusHealth | None, str]:
        """What the kernel says of ``bus`` (state, counters: a socketcan bus), or None and why it
        cannot say (another interface; no such interface)."""
        cfg = self.config.bus(bus)
        if cfg.interface != "socketcan":
            return None, f"{cfg.interface}: no kernel controller to read"
        try:
            return read_kernel_health(cfg.channel), ""
        except ConfigError as err:
            return None, str(err)

    def _supervise(self) -> None:
        periods = itertools.count()
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
            if next(periods) % BUS_CHECK_PERIODS:
                continue
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
                    if self.recorder is not None:
                        self.recorder.process_late()
                    self._rate_limited.log(logging.WARNING, ("late", name),
                                           "bus %s: host heartbeat %.0f ms late (period %.0f ms): this process is"
                                           " starved; the drives stop by themselves when it is later than their"
                                           " host timeout", name, (now - handle.last_beat - bus_cfg.host_heartbeat_s)
                                           * 1000, bus_cfg.host_heartbeat_s * 1000)
                handle.last_beat = now
                handle.next_beat = max(handle.next_beat + bus_cfg.host_heartbeat_s, now)

    def _supervise_bus(self, name: str, handle: BusHandle, now: float) -> None:
        """A bus is lost when its receive thread failed, or when every drive on it lost its
        heartbeat and nothing at all arrived for a consumer time (a socketcand server that died,
        an unplugged adapter). A bus the driver opened itself is then reconnected with back-off
        on the bus's worker and its drives are booted again (not re-armed: commands are refused
        until someone enables them)."""
        bus_cfg = self.config.bus(name)
        self._queue_full(name, handle)
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

    def _queue_full(self, name: str, handle: BusHandle) -> None:
        """Sends the kernel refused for a full transmit queue (ENOBUFS; each retried) are counted
        and said, at a bounded rate; they are in /diagnostics too."""
        full = handle.network.tx_queue_full
        if full != handle.reported_queue_full:
            handle.reported_queue_full = full
            self._rate_limited.log(logging.WARNING, ("queue", name), "bus %s: transmit queue full (ENOBUFS) %d times"
                                   " so far, %d frame(s) given up on: the controller cannot send (no node"
                                   " acknowledging? check cabling, termination and bitrate)", name, full,
                                   handle.network.tx_queue_dropped)

    def _reconnect(self, name: str, handle: BusHandle, drop: bool = False) -> None:
        """On the bus's worker: drop the lost connection (``drop``), open the bus again and boot
        its drives; back off on failure. A kernel interface that is down is waited for (said
        once, when it goes and when it is back), not opened over and over."""
        if drop:
            handle.disconnect()
        bus_cfg = self.config.bus(name)
        if not self._link_up(name, handle):
            handle.next_attempt = time.monotonic() + RECONNECT_MIN_S
            return
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

    def _link_up(self, name: str, handle: BusHandle) -> bool:
        """A kernel interface ready to carry frames as the kernel has it: up and not BUS-OFF (True
        where that cannot be known: not a kernel bus, no netlink). Its going and its coming back
        are each said once; a BUS-OFF controller is left to the kernel's restart-ms (with 0 it
        stays off: said, with the command that restarts it)."""
        health, _ = self.kernel_health(name)
        if health is None:
            return True
        ready = health.link_up and health.state != "BUS-OFF"
        if not ready and not handle.link_down_said:
            handle.link_down_said = True
            why = (f"{health.interface} is down" if not health.link_up else
                   f"{health.interface} is BUS-OFF; the kernel restarts it after restart-ms {health.restart_ms}"
                   if health.restart_ms else f"{health.interface} is BUS-OFF and restart-ms is 0: it stays off"
                   f" until `ip link set {health.interface} type can restart`")
            logger.error("bus %s: link down (%s); the drives' own host watch stops them; waiting for the link, then"
                         " the drives are configured again and left disabled", name, why)
            if self.recorder is not None:
                self.recorder.trigger("link_down", name, text=why)
        elif ready and handle.link_down_said:
            handle.link_down_said = False
            logger.warning("bus %s: link up again (%s %s)", name, health.interface, health.state or "")
        return ready

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
        stop_by_sdo = drive.check_heartbeat(now)  # a lost drive is told to stop (RPDO, NMT) from here
        if stop_by_sdo is not None:
            self._handles[cfg.bus].worker.submit(stop_by_sdo)  # and by SDO, which waits: on the bus's worker
        if drive.lost and not was_lost:
            self._incident("heartbeat_lost", drive, "heartbeat lost; told to stop")
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

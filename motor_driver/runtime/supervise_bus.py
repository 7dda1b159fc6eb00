"""The supervisor's work on buses (part of :class:`motor_driver.runtime.supervisor.Supervisor`, on its
thread): the host heartbeat when it falls due, and about every BUS_CHECK_S a look at each bus (its
connection, error frames, the SYNC job, silence); a lost bus the driver opened is reconnected
with back-off by a job on the bus's worker, which reports back (:class:`BusBack`,
:class:`BusDown`) instead of writing anything of the supervisor's.

Owner: the supervisor thread writes each :class:`BusRecord` (:mod:`motor_driver.drive.ledger`); the
worker's job only opens, closes and boots, through the bus handle's and the drives' methods.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from can_config import RoverConfig
from can_config.errors import BusLostError, ConfigError, MotorError
from motor_driver.bus.adapters import connection_closed, stall_of
from motor_driver.bus.connect import open_bus
from motor_driver.bus.cyclic import DaemonCyclicTask
from motor_driver.bus.handle import BEAT_LOCK_BUSY, RECONNECT_MAX_S, RECONNECT_MIN_S, SEND_FAILING_BEATS, BusHandle
from motor_driver.bus.link import KernelBusHealth, read_kernel_health
from motor_driver.drive import Drive
from motor_driver.drive.ledger import BusBack, BusDown, BusRecord, DriveRecord, Event
from motor_driver.process.jobs import JobFaults, brief_error, cause_of
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.recording.flight import FlightRecorder

logger = logging.getLogger(__name__)

#: A bus is looked at (its connection, error frames, the SYNC job, silence) every this many
#: supervisor periods of SUPERVISOR_PERIOD_S (BUS_CHECK_S, at most a period later: the
#: supervisor's wait_s): a bus that goes is marked lost within 60 ms, inside the drives' own 150 ms host
#: timeout, which is what stops them; every period it would be half the supervisor's CPU (a
#: socket peek and a select per bus). Drives are looked at every period.
BUS_CHECK_PERIODS = 5


@dataclass(eq=False)
class BusSupervision:
    """The buses' part of the supervisor (composed into it, same thread). ``drives`` and
    ``runtimes`` are the supervisor's, read here; ``drive_gone`` and ``report`` are its ways back."""

    config: RoverConfig
    handles: dict[str, BusHandle]
    recorder: FlightRecorder | None
    rate_limited: RateLimitedLog
    drives: dict[str, Drive]
    records: dict[str, DriveRecord]
    drive_gone: Callable[[Drive], None]
    report: Callable[[Event], None]
    faults: JobFaults = field(default_factory=JobFaults)
    bus_records: dict[str, BusRecord] = field(init=False)

    def __post_init__(self) -> None:
        self.bus_records = {name: BusRecord() for name in self.handles}

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

    def beat(self, now: float) -> None:
        """The host heartbeat on every bus that is up, from the supervisor's loop: when the loop
        stops (the process killed, hung, stopped), the heartbeat stops and the drives stop themselves.
        A beat skipped for the send lock (another writer held it a moment: nothing was tried on the
        bus) is tried again the next period (about 10 ms), not a heartbeat period later, which left
        the drive a whole period without one; a send that failed keeps the heartbeat's own cadence
        (a full queue that lets a frame through now and then is still a bus that carries nothing)."""
        for name, handle in self.handles.items():
            rt = self.bus_records[name]
            if now < rt.next_beat or rt.lost:
                continue
            bus_cfg = self.config.bus(name)
            failed = handle.beat(bus_cfg.host_node_id)
            if failed is None:
                rt.send_failing = None
            elif rt.send_failing is None:  # lost once failing long enough (_lost_why)
                rt.send_failing = (now, failed)
            if failed == BEAT_LOCK_BUSY:
                continue
            if rt.last_beat and now - rt.last_beat > 2 * bus_cfg.host_heartbeat_s:
                if self.recorder is not None:
                    self.recorder.process_late()
                self.rate_limited.log(logging.WARNING, ("late", name),
                                       "bus %s: host heartbeat %.0f ms late (period %.0f ms): this process is"
                                       " starved; the drives stop by themselves when it is later than their"
                                       " host timeout", name, (now - rt.last_beat - bus_cfg.host_heartbeat_s)
                                       * 1000, bus_cfg.host_heartbeat_s * 1000)
            rt.last_beat = now
            rt.next_beat = max(rt.next_beat + bus_cfg.host_heartbeat_s, now)

    def supervise_buses(self, now: float) -> None:
        for name, handle in self.handles.items():
            try:
                self._supervise_bus(name, handle, self.bus_records[name], now)
            except Exception as err:
                self.faults.failed("supervisor", f"bus {name}", err)

    def _lost_why(self, name: str, handle: BusHandle, rt: BusRecord, now: float) -> str:
        """Why the bus counts as lost now ('' while it does not): a write to it blocked (the server
        stopped reading), its receive thread failed, the server closed the connection, an error
        frame that loses it, sends that keep failing, or every drive on it lost and nothing at all
        received for a consumer time."""
        exc = handle.network.notifier.exception if handle.network.notifier else None
        drives = [d for d in self.drives.values() if d.config.bus == name]
        if handle.stats.frames != rt.last_frames:
            rt.last_frames, rt.last_rx = handle.stats.frames, now
        silent_for = now - rt.last_rx if rt.last_rx else 0.0
        timeout = max((d.config.heartbeat_timeout_s for d in drives), default=1.0)
        losing = self._bus_error(name, handle, rt)
        failing = rt.send_failing
        stalled = stall_of(handle.bus)  # before the rest: its connection given up reads as closed too
        if stalled:
            return stalled
        if exc is not None:
            return f"receive failed: {brief_error(exc)}"
        if connection_closed(handle.bus):
            return "the server closed the connection"
        if losing:
            return f"error frame: {losing}"
        if failing is not None and now - failing[0] > SEND_FAILING_BEATS * self.config.bus(name).host_heartbeat_s:
            return f"sends fail: {failing[1]}"
        if drives and all(self.records[d.name].lost for d in drives) and silent_for > timeout:
            return f"nothing received for {silent_for:.1f} s"
        return ""

    def _supervise_bus(self, name: str, handle: BusHandle, rt: BusRecord, now: float) -> None:
        """A lost bus the driver opened itself is reconnected with back-off on the bus's worker and
        its drives are booted again (not re-armed: commands are refused until someone enables them)."""
        self._queue_full(name, handle, rt)
        if not rt.lost:
            sync = handle.sync_task
            if isinstance(sync, DaemonCyclicTask) and not sync.keep_alive(now) and rt.job_done():
                rt.job = handle.worker.submit(self.faults.supervised(  # the daemon dropped the SYNC job
                    "sync_restart", f"bus {name}", handle.restart_sync))  # failed: tried again at the next look
            why = self._lost_why(name, handle, rt, now)
            if not why:
                return
            for drive in self.drives.values():  # first: no command passes once the bus counts as lost
                if drive.config.bus == name:
                    self.drive_gone(drive)
            rt.lost, rt.send_failing, rt.backoff_s = True, None, RECONNECT_MIN_S
            logger.error("bus %s lost (%s)", name, why)
            if self.recorder is not None:
                self.recorder.trigger("bus_lost", name, text=why)
            rt.last_beat = 0.0  # no heartbeat while the bus is gone: that is not lateness
            if handle.owned:  # reconnected on the bus's worker: joining a notifier can take a second
                rt.next_attempt = float("inf")  # until the job says when to try again
                rt.job = handle.worker.submit(self._reconnect_job(name, handle, True))
            return
        if not handle.owned or now < rt.next_attempt or not rt.job_done():
            return
        rt.next_attempt = float("inf")
        rt.job = handle.worker.submit(self._reconnect_job(name, handle))

    def bus_event(self, event: Event, now: float) -> None:
        """A reconnect job's result, on the supervisor's thread."""
        if isinstance(event, BusBack):
            rt = self.bus_records[event.bus]
            self._link_said(event.bus, rt, "")
            rt.lost, rt.backoff_s = False, RECONNECT_MIN_S
            logger.warning("bus %s re-established; drives configured again (not enabled)", event.bus)
        elif isinstance(event, BusDown):
            rt = self.bus_records[event.bus]
            self._link_said(event.bus, rt, event.link_down)
            if event.retry_s is None:
                rt.backoff_s = min(max(rt.backoff_s, RECONNECT_MIN_S) * 2, RECONNECT_MAX_S)
                logger.warning("bus %s: %s; next try in %.1f s", event.bus, event.why, rt.backoff_s)
            rt.next_attempt = now + (rt.backoff_s if event.retry_s is None else event.retry_s)

    def _link_said(self, name: str, rt: BusRecord, link_down: str) -> None:
        """A kernel link's going down and its coming back are each said once."""
        if link_down and not rt.link_down_said:
            rt.link_down_said = True
            logger.error("bus %s: link down (%s); the drives' own host watch stops them; waiting for the link, then"
                         " the drives are configured again and left disabled", name, link_down)
            if self.recorder is not None:
                self.recorder.trigger("link_down", name, text=link_down)
        elif not link_down and rt.link_down_said:
            rt.link_down_said = False
            logger.warning("bus %s: link up again", name)

    def _bus_error(self, name: str, handle: BusHandle, rt: BusRecord) -> str:
        """Report the newest error frame that came since the last look (log, flight recorder; the
        count is in /diagnostics); return what it says when one since then loses the bus (bus-off,
        no ACK: the driver's frames reach no drive), else ''."""
        stats = handle.stats
        last = stats.last_error
        if last is None or last[0] <= rt.reported_error:
            return ""
        rt.reported_error = last[0]
        losing = stats.last_losing_error > rt.reported_losing
        rt.reported_losing = stats.last_losing_error
        logger.log(logging.ERROR if losing else logging.WARNING, "bus %s: error frame: %s (%d so far)", name,
                   last[1].text, stats.error_frames)
        if self.recorder is not None:
            self.recorder.trigger("bus_error", name, code=last[1].classes, text=last[1].text)
        return last[1].text if losing else ""

    def _queue_full(self, name: str, handle: BusHandle, rt: BusRecord) -> None:
        """Sends the kernel refused for a full transmit queue (ENOBUFS; each retried) are counted
        and said, at a bounded rate; they are in /diagnostics too."""
        full = handle.network.tx_queue_full
        if full != rt.reported_queue_full:
            rt.reported_queue_full = full
            self.rate_limited.log(logging.WARNING, ("queue", name), "bus %s: transmit queue full (ENOBUFS) %d times"
                                   " so far, %d frame(s) given up on: the controller cannot send (no node"
                                   " acknowledging? check cabling, termination and bitrate)", name, full,
                                   handle.network.tx_queue_dropped)

    # ------------------------------------------------------------------ the bus's worker
    def _reconnect_job(self, name: str, handle: BusHandle, drop: bool = False) -> Callable[[], None]:
        """The reconnect as a supervised job: whatever it raises is counted, logged and reported
        as a failed try (the connection dropped, the back-off doubles), never left in its Future
        with ``next_attempt`` at infinity."""

        def failed(err: BaseException) -> None:
            try:
                handle.disconnect()
            finally:
                self.report(BusDown(name, None, "", f"reconnect failed unexpectedly ({cause_of(err)})"))

        return self.faults.supervised("reconnect", f"bus {name}", lambda: self._reconnect(name, handle, drop), failed)

    def _reconnect(self, name: str, handle: BusHandle, drop: bool = False) -> None:
        """On the bus's worker: drop the lost connection (``drop``), open the bus again and boot
        its drives; each outcome is reported to the supervisor (back-off is its own). A kernel
        interface that is down is waited for, not opened over and over."""
        if drop:
            handle.disconnect()
        link_down = self._link_down(name)
        if link_down:
            self.report(BusDown(name, RECONNECT_MIN_S, link_down, "link down"))
            return
        try:
            handle.reconnect(open_bus(self.config.bus(name).bus_kwargs(), connect_timeout_s=0.0))  # one try
        except (can.CanError, OSError, ValueError, TimeoutError, BusLostError) as err:
            self.report(BusDown(name, None, "", f"reconnect failed ({brief_error(err)})"))
            return
        try:
            for drive in (d for d in self.drives.values() if d.config.bus == name):
                drive.boot.boot(reset=True)
        except BusLostError as err:  # opened, but nothing goes out (an interface still down)
            handle.disconnect()
            self.report(BusDown(name, None, "", f"still not usable ({brief_error(err)})"))
            return
        except MotorError as err:
            logger.error("bus %s is back but a drive did not boot: %s; retrying", name, err)
            handle.disconnect()
            self.report(BusDown(name, RECONNECT_MIN_S, "", "a drive did not boot"))
            return
        handle.start_sync()
        self.report(BusBack(name))

    def _link_down(self, name: str) -> str:
        """Why a kernel interface cannot carry frames as the kernel has it (down, BUS-OFF), or ''
        (ready, or not knowable: not a kernel bus, no netlink). A BUS-OFF controller is left to the
        kernel's restart-ms (with 0 it stays off: said, with the command that restarts it)."""
        health, _ = self.kernel_health(name)
        if health is None or (health.link_up and health.state != "BUS-OFF"):
            return ""
        return (f"{health.interface} is down" if not health.link_up else
                f"{health.interface} is BUS-OFF; the kernel restarts it after restart-ms {health.restart_ms}"
                if health.restart_ms else f"{health.interface} is BUS-OFF and restart-ms is 0: it stays off"
                f" until `ip link set {health.interface} type can restart`")

"""The supervisor (thread ``rovercan-supervisor``), never blocks: the host heartbeat on every bus,
the drives' heartbeats, the velocity watchdog and the limit guard, another master, every period;
the buses (lost, error frames, the SYNC job) about every BUS_CHECK_S (:mod:`motor_driver.runtime.supervise_bus`).
Re-boots and reconnects run on the bus's worker.

Its period (:meth:`Supervisor.wait_s`): SUPERVISOR_PERIOD_S while anything wants a look that often
(a live velocity or torque command's watchdog and limit guard, a drive lost, booting, stopping or
another master's, a bus lost or failing); otherwise the supervisor is quiet and waits until the
first thing falls due (a host heartbeat, a drive's heartbeat timeout, a node guard), at most
QUIET_WAIT_MAX_S. What changes meanwhile wakes it at once (:meth:`Supervisor.wake`): a report or
an event handed over, a command going live, another master's sign. Its wake-ups, not its checks,
were its cost (docs/performance.md): a quiet rover's supervisor wakes at the host heartbeat's
period instead of every SUPERVISOR_PERIOD_S.

Owner: the :class:`Supervisor`, on its thread, alone writes the ledger's records
(:mod:`motor_driver.drive.ledger`): one :class:`DriveRecord` per drive and one :class:`BusRecord`
per bus. The receive thread posts what it heard (:meth:`Supervisor.post`, never waits); a boot
or a reconnect on a worker reports its result (:meth:`Supervisor.report`) and goes on once the
supervisor applied it, within a period. Its jobs on a worker are supervised
(:mod:`motor_driver.process.jobs`): what one raises unexpectedly is counted, logged and retried. A period
that raises is counted and logged and the loop goes on; SUPERVISOR_FAILURES_MAX periods in a row
end the loop: every drive is told to stop (quick stop through its command channel) and
``ended`` says why (an ERROR in /diagnostics), written once by this thread as it ends. Before its thread starts (the boots of ``start``) and
after it ended, a report is applied on the caller's thread, under the supervisor's lock: nothing
else writes then. It changes a drive only through the drive's parts, none of which waits (the
channel's lock is tried; a busy channel is tried again the next period).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future

from can_config import RoverConfig
from can_config.errors import MotorError
from can_config.objects import NmtState
from motor_driver.bus.handle import BusHandle
from motor_driver.bus.traffic import FOREIGN_HOLD_S, FOREIGN_RELEASE_S
from motor_driver.drive import Drive
from motor_driver.drive.constants import REBOOT_RETRY_S
from motor_driver.drive.ledger import (
    Booted,
    Booting,
    BootRestarted,
    DriveRecord,
    Event,
    Heard,
    RebootFailed,
    RestoreFailed,
    SupervisorPort,
)
from motor_driver.process.held import READ_BEHIND_MAX_S
from motor_driver.process.jobs import JobFaults, cause_of
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.protocol.cia402 import Command
from motor_driver.recording.flight import FlightRecorder
from motor_driver.runtime.supervise_bus import BUS_CHECK_PERIODS, BusSupervision

logger = logging.getLogger(__name__)

SUPERVISOR_PERIOD_S = 0.01
#: How near a drive's EMCY 0x8130 and its NMT change must come for the EMCY to explain it, s (at
#: least three of its heartbeat periods: the change is said by its next heartbeat).
HOST_LOSS_NMT_S = 1.0
#: The buses are looked at about this often: at a period at most half a period early (a heartbeat's,
#: so that a quiet supervisor does both in one wake-up), at most a period late.
BUS_CHECK_S = BUS_CHECK_PERIODS * SUPERVISOR_PERIOD_S
#: The longest a quiet supervisor waits for its next period (s).
QUIET_WAIT_MAX_S = BUS_CHECK_S
#: A drive's heartbeat overdue by the clock is judged by how far the bus's receive thread has read
#: (Supervisor._read_behind) for at most READ_BEHIND_MAX_S past its timeout (s); then by the clock
#: alone (a receive thread that stopped reading). The same bound as an SDO answer's wait (held.ReadBehind).
#: Periods in a row that raise before the loop ends (one bad period is counted and passed over).
SUPERVISOR_FAILURES_MAX = 5
#: How long the loop's end waits for each drive's command channel to send the stop.
END_STOP_LOCK_S = 0.1

__all__ = ["BUS_CHECK_PERIODS", "BUS_CHECK_S", "QUIET_WAIT_MAX_S", "SUPERVISOR_PERIOD_S", "Supervisor"]


class Supervisor:
    """The one writer of the records of every drive and bus of a driver."""

    def __init__(self, config: RoverConfig, handles: dict[str, BusHandle], recorder: FlightRecorder | None) -> None:
        self.config = config
        self.handles = handles
        self.recorder = recorder
        self.drives: dict[str, Drive] = {}
        self.records: dict[str, DriveRecord] = {}
        self.faults = JobFaults()
        self._behind_log = RateLimitedLog(logger)  # a starved driver's "behind" and "caught up", per drive
        self.bus = BusSupervision(config, handles, recorder, RateLimitedLog(logger), self.drives, self.records,
                                  self._drive_gone, self.report, self.faults)
        #: why the loop ended on its own ('' while it runs, or stopped by stop()): this thread's, once
        self.ended = ""
        self._inbox: queue.SimpleQueue[tuple[Event | Callable[[], object], Future[object] | None]] = \
            queue.SimpleQueue()
        self._lock = threading.Lock()  # the inbox's: running or not, and a report applied inline
        self._running = False
        self._stop = threading.Event()
        self._wake = threading.Event()  # set by wake(): the next period now
        self._bus_checked = -float("inf")  # when the buses were last looked at (monotonic)
        self._thread: threading.Thread | None = None
        self._take_over = False
        for handle in handles.values():
            handle.foreign.set_wake(self.wake)  # another master's sign: judged now

    # ------------------------------------------------------------------ the ports
    def port(self, drive: str) -> tuple[DriveRecord, SupervisorPort]:
        """A new drive's record (read by its parts) and its way to hand results here."""
        record = self.records[drive] = DriveRecord()
        return record, SupervisorPort(self.post, self.report, self.wake)

    def add(self, drive: Drive) -> None:
        self.drives[drive.name] = drive

    def wake(self) -> None:
        """The next period now (never waits; any thread): something it watches changed."""
        self._wake.set()

    def post(self, event: Event) -> None:
        """Hand an event over without waiting (the receive thread): applied at the next period, now."""
        self._inbox.put((event, None))
        self.wake()

    def report(self, event: Event) -> None:
        """Hand a result over and return once it is applied (a worker, a caller's thread)."""
        self.call(lambda: self._apply(event, time.monotonic()))

    def call(self, fn: Callable[[], object]) -> object:
        """Run ``fn`` on the supervisor's thread (inline when it does not run) and return its result."""
        if threading.current_thread() is self._thread:
            return fn()
        reply: Future[object] = Future()
        with self._lock:
            if not self._running:
                return fn()
            self._inbox.put((fn, reply))
            self.wake()
        return reply.result()

    # ------------------------------------------------------------------ the thread
    def start(self, take_over: bool) -> None:
        self._take_over = take_over  # another master's traffic is then expected
        with self._lock:
            self._running = True
        self._thread = threading.Thread(target=self._run, daemon=True, name="rovercan-supervisor")
        self._thread.start()

    @property
    def dead(self) -> bool:
        """Its thread was started and has ended without stop() (read by /diagnostics: an ERROR)."""
        return self._thread is not None and not self._thread.is_alive() and not self._stop.is_set()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self.wake()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=timeout_s)

    def _run(self) -> None:
        try:
            self._supervise()
        except Exception as err:
            self._end(err)
        finally:
            with self._lock:
                self._running = False
                self._drain(time.monotonic())  # every report handed over before this is answered

    def _supervise(self) -> None:
        failing = 0
        wait = SUPERVISOR_PERIOD_S
        while True:
            self._wake.wait(wait)
            self._wake.clear()  # before the period: a wake during it brings the next one at once
            if self._stop.is_set():  # (stop() sets it before it wakes: never missed)
                return
            try:
                self._period(time.monotonic())
                failing = 0
            except Exception as err:
                failing += 1
                self.faults.failed("supervisor", "supervisor", err)
                if failing >= SUPERVISOR_FAILURES_MAX:
                    raise
            try:
                wait = self.wait_s(time.monotonic())
            except Exception as err:  # the period it would judge: as before this was judged at all
                wait = SUPERVISOR_PERIOD_S
                self.faults.failed("supervisor", "supervisor: its next period", err)

    def wait_s(self, now: float) -> float:
        """How long the loop waits for its next period (module docstring): SUPERVISOR_PERIOD_S while
        anything wants a look every period, else until the first thing falls due, at least
        SUPERVISOR_PERIOD_S and at most QUIET_WAIT_MAX_S. The buses' look is due BUS_CHECK_S after
        the last, a period later at most (it rides a heartbeat's period when one comes a little
        before: :meth:`_period`)."""
        due = min(now + QUIET_WAIT_MAX_S, self._bus_checked + BUS_CHECK_S + SUPERVISOR_PERIOD_S)
        for rt in self.bus.bus_records.values():
            if rt.lost or not rt.job_done() or rt.send_failing is not None:
                return SUPERVISOR_PERIOD_S  # a bus lost, reconnecting, restarting its SYNC, failing to send
            due = min(due, rt.next_beat)
        since = now - FOREIGN_HOLD_S
        for drive in self.drives.values():
            record = self.records[drive.name]
            job = record.reboot_job
            if drive.channel.velocity_commanded or not record.booted or record.lost or record.lost_since \
                    or record.stop_pending or record.forget_pending or record.reboot_wanted or record.read_behind \
                    or record.foreign_master or (job is not None and not job.done()) \
                    or record.behind_back[0] > since or drive.cache.behind_back[0] > since \
                    or (not self._take_over and self.handles[drive.config.bus].foreign.newest > since):
                # (told to take the bus over, another master's traffic is expected: not looked at)
                return SUPERVISOR_PERIOD_S
            heard = drive.cache.last_heartbeat
            if heard:
                due = min(due, heard + drive.config.heartbeat_timeout_s)
            if drive.cache.guarding:
                due = min(due, record.next_guard)
        return min(max(due - now, SUPERVISOR_PERIOD_S), QUIET_WAIT_MAX_S)

    def _end(self, err: Exception) -> None:
        """The loop failed SUPERVISOR_FAILURES_MAX periods in a row: nothing watches the drives any
        more (no host heartbeat either): each is told to stop now, and ``ended`` says why."""
        self.ended = (f"the supervisor ended after {SUPERVISOR_FAILURES_MAX} failed periods in a row"
                      f" ({cause_of(err)}); every drive was told to stop; restart the driver")
        logger.error("%s", self.ended)
        for drive in self.drives.values():
            try:
                if not drive.channel.stop(Command.QUICK_STOP, "the supervisor ended", timeout_s=END_STOP_LOCK_S):
                    logger.error("%s: not told to stop (its command channel stayed busy); it stops by itself on"
                                 " host loss", drive.name)
            except Exception as stop_err:  # the bus may be the trouble: the drive's host watch stops it
                logger.error("%s: not told to stop (%s); it stops by itself on host loss", drive.name,
                             cause_of(stop_err))

    def _period(self, now: float) -> None:
        """One period: reports, host heartbeat, recorder sample, each drive, and about every
        BUS_CHECK_S the buses."""
        self._drain(now)
        self.bus.beat(now)
        if self.recorder is not None and self.recorder.wants_sample(now):
            self.recorder.sample([d.snapshot() for d in self.drives.values()])
        for drive in self.drives.values():
            try:
                self._supervise_drive(drive, self.records[drive.name], now)
            except MotorError as err:
                logger.error("supervisor: %s", err)
            except Exception as err:
                self.faults.failed("supervisor", f"supervisor: {drive.name}", err)
        if now - self._bus_checked < BUS_CHECK_S - SUPERVISOR_PERIOD_S / 2:
            return
        self._bus_checked = now
        self.bus.supervise_buses(now)

    def _drain(self, now: float) -> None:
        while True:
            try:
                item, reply = self._inbox.get_nowait()
            except queue.Empty:
                return
            try:
                if callable(item):
                    result = item()
                else:
                    self._apply(item, now)
                    result = None
            except Exception as err:
                if reply is None:
                    self.faults.failed("supervisor", f"supervisor: {item} not applied", err)
                else:
                    reply.set_exception(err)
                continue
            if reply is not None:
                reply.set_result(result)

    # ------------------------------------------------------------------ what others found
    def _apply(self, event: Event, now: float) -> None:
        if isinstance(event, Heard):
            self._heard(event)
        elif isinstance(event, BootRestarted):
            record = self.records[event.drive]
            record.boot_restarts += 1
            record.boot_restart_why = event.why
        elif isinstance(event, RestoreFailed):
            self.faults.failed("restore_enable", f"{event.drive}: enabling it again after its re-configuration",
                               event.error)
        elif isinstance(event, (Booting, Booted, RebootFailed)):
            record = self.records[event.drive]
            record.booted = isinstance(event, Booted)
            if isinstance(event, Booted):
                self._booted(event, record, now)
            elif isinstance(event, Booting):
                record.reboot_wanted = False
            else:
                record.reboot_wanted, record.reboot_at = True, now + event.retry_s
                record.reconfigure_failures += 1
                record.reconfigure_error = event.error
        else:
            self.bus.bus_event(event, now)

    def _booted(self, event: Booted, record: DriveRecord, now: float) -> None:
        """A boot ended. A boot-up heard after the boot's last look (its report was on its way) is
        a reset that undid the configuration: not booted, configured again."""
        record.lost, record.lost_since, record.reboot_wanted = False, 0.0, False
        record.booted_at = now
        record.bootups_confirmed = event.bootups
        drive = self.drives.get(event.drive)
        if drive is not None:
            record.host_loss_emcys_spent = drive.cache.host_loss_emcys
        if drive is not None and drive.cache.bootups > event.bootups:
            why = "it sent boot-up as its boot ended"
            logger.warning("node %d (%s): %s: it reset; it will be configured again", drive.node_id, drive.name, why)
            record.boot_restarts += 1
            record.boot_restart_why = why
            self._configure_again(record)

    def _heard(self, event: Heard) -> None:
        """A heartbeat the receive thread posted: a boot-up, a lost drive heard again, or a change of
        NMT state, this driver's doing (an NMT command it sent asks for it) or another master's."""
        drive, record = self.drives[event.drive], self.records[event.drive]
        if event.state == NmtState.BOOTUP:
            # one the last configuration accounted for is history; one during a boot is the boot's
            # to see (it starts its configuration again), or this thread's when its Booted comes
            if event.bootups > record.bootups_confirmed and record.booted:
                logger.warning("node %d (%s) sent boot-up: it power-cycled or reset; it will be configured again",
                               drive.node_id, drive.name)
                self._configure_again(record)
            return
        if event.at <= record.booted_at:
            return  # heard before the boot that followed it ended (posted while the supervisor was not running)
        name = drive.cache.nmt_state if event.state != NmtState.OPERATIONAL else "OPERATIONAL"
        if record.lost and record.booted:
            if event.state == NmtState.OPERATIONAL and \
                    drive.watch.nmt_ledger.in_flight(event.state, event.at, drive.config.heartbeat_period_s):
                # sent before it obeyed the NMT stop this driver tells a lost drive every period: it
                # is about to go STOPPED, not back (an enable now would meet a stopped node); its
                # next heartbeat says which
                return
            if event.state == NmtState.OPERATIONAL:
                logger.warning("node %d (%s): heartbeat back after %.1f s lost; it was told to stop %d times; enable"
                               " it again to drive it", drive.node_id, drive.name,
                               event.at - record.lost_since if record.lost_since else 0.0, record.lost_stops)
                record.lost = False
            else:
                logger.warning("node %d (%s): heard again in NMT %s (told to stop while lost); configuring it again,"
                               " left disabled", drive.node_id, drive.name, name)
                self._configure_again(record)
            record.lost_since = 0.0
            return
        if not record.booted or record.lost or event.state == NmtState.OPERATIONAL or event.was != "OPERATIONAL":
            return
        if drive.watch.nmt_ledger.in_flight(event.state, event.at, drive.config.heartbeat_period_s):
            return  # sent before it obeyed this driver's newest NMT command
        if drive.watch.nmt_ledger.explains(event.state):
            command, when = drive.watch.nmt_ledger.last
            logger.warning("node %d (%s): now NMT %s, as this driver told it (%s, %.0f ms before); configuring it"
                           " again, left disabled", drive.node_id, drive.name, name,
                           command.name if command is not None else "?", (event.at - when) * 1000)
            self._configure_again(record)
        elif self._own_comm_error(drive, record, event.at):
            # its own doing: a communication error (this host's heartbeat lost, EMCY 0x8130) takes a
            # drive whose 0x1029:1 says so to PRE-OPERATIONAL or STOPPED; not another master's command
            logger.warning("node %d (%s): now NMT %s after it heard no heartbeat from this host (EMCY 0x8130: its"
                           " communication-error behaviour, 0x1029); configuring it again, left disabled. Was this"
                           " process stalled, or the bus cut?", drive.node_id, drive.name, name)
            self._configure_again(record)
        else:
            record.behind_back = (event.at, f"node {drive.node_id} went {name} without an NMT command from"
                                             " this driver")

    @staticmethod
    def _own_comm_error(drive: Drive, record: DriveRecord, at: float) -> bool:
        """An NMT change ``at`` explained by the drive's own EMCY 0x8130 (this host's heartbeat lost):
        one not yet used to explain a change, since its last boot, heard within HOST_LOSS_NMT_S of the
        change (they come together; a starved receive thread hands both on at once). Used once: a
        later change (another master's) is not explained by an old one."""
        cache = drive.cache
        if cache.host_loss_emcys <= record.host_loss_emcys_spent or abs(at - cache.host_loss_at) > max(
                HOST_LOSS_NMT_S, 3 * drive.config.heartbeat_period_s):
            return False
        record.host_loss_emcys_spent = cache.host_loss_emcys
        return True

    @staticmethod
    def _configure_again(record: DriveRecord) -> None:
        record.booted = record.read_behind = False
        record.reboot_wanted = True

    # ------------------------------------------------------------------ each drive, each period
    def _supervise_drive(self, drive: Drive, record: DriveRecord, now: float) -> None:
        cfg = drive.config
        self._check_foreign(drive, record, now)
        if record.foreign_master:
            return  # nothing of ours goes to a drive another master drives (no re-boot, no watchdog)
        if record.forget_pending:
            record.forget_pending = not drive.channel.forget_commanded(timeout_s=0.0)
        if record.reboot_wanted:
            job = record.reboot_job
            if (job is None or job.done()) and now >= record.reboot_at and not self.bus.bus_records[cfg.bus].lost:
                record.reboot_wanted = False
                record.reboot_job = self.handles[cfg.bus].worker.submit(self.faults.supervised(
                    "reconfigure", drive.name, drive.boot.reconfigure,
                    lambda err: self.report(RebootFailed(drive.name, REBOOT_RETRY_S))))
            return
        self._check_heartbeat(drive, record, now)
        if drive.boot.host_loss_stops != record.host_loss_seen:
            record.host_loss_seen = drive.boot.host_loss_stops
            self._incident("host_loss_stop", drive, "the drive had stopped itself: the host was gone (0x8130)")
        channel = drive.channel
        if not channel.velocity_commanded:
            return  # the watchdog and the limit guard watch a live velocity or torque command only
        if now - channel.last_velocity_cmd > cfg.watchdog_s:
            logger.warning("%s: no velocity command for %.0f ms (watchdog %.0f ms); stopping",
                           drive.name, (now - channel.last_velocity_cmd) * 1000, cfg.watchdog_s * 1000)
            if drive.limits.stop_velocity():
                self._incident("watchdog_stop", drive, f"no command for {cfg.watchdog_s * 1000:.0f} ms")
        drive.limits.guard_limits()

    def _check_heartbeat(self, drive: Drive, record: DriveRecord, now: float) -> None:
        """Guard a guarded drive when due; declare the drive lost when its heartbeat is overdue and
        tell it to stop, again every heartbeat period while it stays lost (the SDO copy of the
        stop, which waits, on the bus's worker)."""
        cfg, cache = drive.config, drive.cache
        if cache.guarding and now >= record.next_guard and not record.lost_since:  # a lost drive's life guard trips
            record.next_guard = max(record.next_guard + cfg.heartbeat_period_s, now)
            drive.watch.send_guard()
        heard = cache.last_heartbeat  # read once: the receive thread may renew it meanwhile
        if record.booted and not record.lost and heard and now - heard > cfg.heartbeat_timeout_s:
            if self._read_behind(drive, record, heard, now):
                return
            record.read_behind = False
            record.lost, record.lost_since = True, now
            logger.error("node %d (%s): heartbeat lost (none for %.0f ms, consumer time %.0f ms); telling it to stop"
                         " (quick stop by RPDO and SDO, NMT stop) until it is heard again", drive.node_id, drive.name,
                         (now - heard) * 1000, cfg.heartbeat_timeout_s * 1000)
            self._stop_lost(drive, record, now)
            self.handles[cfg.bus].worker.submit(self.faults.supervised(  # its RPDO copy is repeated meanwhile
                "stop_by_sdo", drive.name, drive.watch.quick_stop_lost_by_sdo))
            self._incident("heartbeat_lost", drive, "heartbeat lost; told to stop")
        elif record.lost_since and record.booted and (now >= record.next_stop or record.stop_pending):
            self._stop_lost(drive, record, now)
        elif record.read_behind:  # heard in time once the receive thread had read that far (or re-booting)
            record.read_behind = False
            if record.booted and not record.lost:
                self._behind_log.log(logging.INFO, (drive.name, "caught up"), "%s: its heartbeat read after all"
                                     " (the receive thread caught up); not lost", drive.name)

    def _read_behind(self, drive: Drive, record: DriveRecord, heard: float, now: float) -> bool:
        """Whether a heartbeat overdue by this thread's clock (read at ``heard``) is the bus's
        receive thread's lateness rather than the drive's silence. The silence is proven when that
        thread has read a frame the bus stamped a heartbeat timeout after the drive's last
        heartbeat (frames come in order), or found its socket empty a timeout after it read that
        heartbeat (a silent bus: :attr:`BusStats.idle_at`). Until then the period is not judged:
        a starved reader must not stop drives that spoke. Past READ_BEHIND_MAX_S the clock
        judges alone (a receive thread that no longer reads): the drive is declared lost as before.
        A node-guarded drive is judged by the clock alone: it answers only when asked, and a driver
        held as a whole asked nothing (its own life guard stopped it meanwhile)."""
        if drive.cache.guarding:
            return False
        timeout = drive.config.heartbeat_timeout_s
        stats = self.handles[drive.config.bus].stats
        # the receive thread writes a heartbeat's stamp, then read_to and idle_at: read the other way
        # round, and the heartbeat once more, so that no stamp older than what they cover is paired
        read_to, idle_at = stats.read_to, stats.idle_at
        stamp = drive.cache.heartbeat_stamp
        if drive.cache.last_heartbeat != heard:
            return True  # heard meanwhile: the next period judges the new one
        overdue_s = now - heard
        if not stamp or read_to - stamp > timeout or idle_at - heard > timeout \
                or overdue_s > timeout + READ_BEHIND_MAX_S:
            return False
        if not record.read_behind:
            record.read_behind = True
            record.read_behind_episodes += 1
            self._behind_log.log(logging.WARNING, (drive.name, "behind"), "%s: no heartbeat read for %.0f ms"
                                 " (timeout %.0f ms), but the receive thread of %s has read only %.0f ms of the bus"
                                 " past its last one: this driver is behind (a starved process), not the drive"
                                 " silent; judged once it has read that far", drive.name, overdue_s * 1000,
                                 timeout * 1000, drive.config.bus, max(read_to - stamp, 0.0) * 1000)
        return True

    @staticmethod
    def _stop_lost(drive: Drive, record: DriveRecord, now: float) -> None:
        record.next_stop = now + drive.config.heartbeat_period_s
        record.lost_stops += 1
        record.stop_pending = not drive.watch.stop_lost()  # a busy channel: its RPDO stop next period

    def _check_foreign(self, drive: Drive, record: DriveRecord, now: float) -> None:
        """Another master on the drive's bus (within FOREIGN_HOLD_S): mark it; once it has been
        quiet for FOREIGN_RELEASE_S, clear the mark and configure the drive again (not enabled)."""
        if self._take_over:
            return  # told to take the bus over: the other master's traffic is expected
        foreign = self.handles[drive.config.bus].foreign
        since = now - FOREIGN_HOLD_S
        evidence = foreign.evidence(drive.node_id, since)
        changes = (record.behind_back, drive.cache.behind_back)
        if not evidence and not record.foreign_master and changes[0][0] <= since and changes[1][0] <= since:
            return  # nothing of another master's, none marked: the usual answer, without building one
        evidence = "; ".join(filter(None, (evidence, *(what for when, what in changes if when > since))))
        if evidence and not record.foreign_master:
            stopped = drive.watch.lose_control(evidence)
            if stopped is None:
                return  # the channel was busy: next period
            record.foreign_master = evidence
            if stopped:  # an SDO waits: on the bus's worker
                self.handles[drive.config.bus].worker.submit(self.faults.supervised(
                    "stop_by_sdo", drive.name, lambda: drive.watch.quick_stop_by_sdo(now)))
        elif evidence:
            record.foreign_master = evidence
        elif record.foreign_master and not foreign.evidence(drive.node_id, now - FOREIGN_RELEASE_S) \
                and max(when for when, _ in changes) <= now - FOREIGN_RELEASE_S:
            logger.warning("%s (node %d): the other master is gone; configuring the drive again (not enabled)",
                           drive.name, drive.node_id)
            record.foreign_master = ""
            self._configure_again(record)

    def _drive_gone(self, drive: Drive) -> None:
        """The drive's bus is gone: lost, not booted; nothing is commanded until it is booted again."""
        record = self.records[drive.name]
        record.lost, record.booted, record.lost_since, record.read_behind = True, False, 0.0, False
        record.forget_pending = not drive.channel.forget_commanded(timeout_s=0.0)

    def _incident(self, kind: str, drive: Drive, text: str) -> None:
        if self.recorder is not None:
            self.recorder.trigger(kind, drive.config.bus, node=drive.node_id, drive=drive.name, text=text)

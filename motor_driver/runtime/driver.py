"""The motor driver: every configured bus and drive in one process.

Per bus: a python-can bus (opened from config, or given), a canopen ``Network`` (its notifier
thread runs the PDO callbacks), a SYNC producer outside this interpreter where the bus has a
timer of its own (the socketcand daemon's cyclic job, :mod:`motor_driver.bus.cyclic`; the kernel's
BCM through python-can's periodic send on SocketCAN; else python-can's thread), and a worker
thread for the bus's blocking jobs (re-boot of a drive that reset, reconnection of a lost bus).

Threads and what they own:
- the notifier thread of each bus (canopen/python-can): decodes frames into each Drive's
  received state and notifies waiters; it sends nothing but the set-point handshake's reply, and
  posts the heartbeats that may change a judgement to the supervisor.
- the supervisor thread (``rovercan-supervisor``, :class:`motor_driver.runtime.supervisor.Supervisor`),
  period SUPERVISOR_PERIOD_S while anything is live, else when something falls due (woken by a
  change), never blocks: produces the host heartbeat on every bus, checks the
  drives' heartbeats, runs the velocity watchdog and the limit guard, notices lost buses and hands
  re-boots and reconnects to the bus's worker. It alone writes the ledger's records (lost, booted,
  another master, reconnect and back-off: :mod:`motor_driver.drive.ledger`); ``bus_lost`` reads it.
- one worker per bus (``rovercan-<bus>``): the re-boots and reconnects, one at a time; each
  reports its result to the supervisor.
- the caller's threads: commands, each decided and sent through the drive's command channel
  (its one lock, held only to decide and send a frame).
- the flight recorder's writer (``rovercan-recorder``, :mod:`motor_driver.recording.flight`): the
  others append frames, states and incidents to it without waiting; it writes the files.

The host heartbeat (node ``host_node_id``, every ``host_heartbeat_ms``) is sent by the
supervisor loop itself, not by a kernel timer: it proves that the driver is alive, so a killed,
hung or stopped process falls silent and every drive, told at boot to watch it (0x1016, 0x6007),
stops by itself within its consumer time.

Safe by default: start() boots and configures but enables only drives with
``arm_on_start`` (none while motion is held: :meth:`MotorDriver.hold_motion`); close()
quick-stops and disables every drive, stops SYNC, stops threads, and closes the buses it
opened, in that order.

What lives where: :mod:`motor_driver.bus.connect` (opening a bus), :mod:`motor_driver.bus.traffic`
(bus statistics, another master), :mod:`motor_driver.bus.handle` (one bus: network, SYNC,
worker), :mod:`motor_driver.runtime.supervisor` (the supervisor's period), this module (the
lifecycle: start, safe stop, close).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager
from typing import NamedTuple

import can

from can_config import RoverConfig, load_drive_od
from can_config.errors import BusLostError, ConfigError, MotorError
from motor_driver.bus.adapters import GuardedNetwork, Rejected, quiet_dependency_tracebacks
from motor_driver.bus.connect import (
    CONNECT_TIMEOUT_S,
    HANDSHAKE_TIMEOUT_S,
    OPEN_ATTEMPTS,
    carries_remote_frames,
    is_kernel_bus,
    open_bus,
    wait_for_server,
)
from motor_driver.bus.handle import BusHandle, sync_daemon
from motor_driver.bus.link import KernelBusHealth
from motor_driver.bus.load import MAX_LOAD, WARN_LOAD, plan_load
from motor_driver.bus.traffic import (
    FOREIGN_HOLD_S,
    SYNC_RATE_WINDOW_S,
    BusStats,
    ForeignTraffic,
    look_for_master,
    look_window_s,
    other_master_error,
)
from motor_driver.diagnostics.health import Health, jobs_health
from motor_driver.drive import Drive, DriveState
from motor_driver.process.stop import teardown
from motor_driver.protocol.cia402 import State
from motor_driver.recording.flight import FlightRecorder
from motor_driver.runtime.supervisor import SUPERVISOR_PERIOD_S, Supervisor

logger = logging.getLogger(__name__)


#: The safe stop's wait for every drive's quick-stop ramp, together, before their voltage goes, s:
#: within the stop grace a launcher or a container gives the process (5 s before SIGTERM).
BRAKE_WAIT_MAX_S = 3.0


class StopReport(NamedTuple):
    """What a safe stop could not confirm, one line a drive (``lines``: those of its quick stops
    first, in the drives' order, then those of its voltage cuts), and which of them are lost drives
    (``lost``): a drive lost after its boot was sent one last quick stop it cannot answer, one lost
    with its bus or being configured again was sent nothing; stopping either again cannot confirm it
    (its power, cable or bus can). ``retry``: the others (a stop refused, timed out or raised), where
    stopping again may help."""

    lines: list[str]
    lost: list[str]

    @property
    def retry(self) -> list[str]:
        return [line for line in self.lines if line not in self.lost]


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
        quiet_dependency_tracebacks()  # a lost bus is one line (the supervisor's), no traceback
        self._handles: dict[str, BusHandle] = {}
        self.drives: dict[str, Drive] = {}
        self._closed = False
        given = dict(buses or {})
        self.recorder = FlightRecorder(config.recorder, {d.name: (d.bus, d.node_id) for d in config.drives},
                                       {b.name: b.channel for b in config.buses},
                                       config.source, config, self._unit_objects) if config.recorder.enabled else None
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
            self.supervisor = Supervisor(config, self._handles, self.recorder)
            self._networks = tuple((name, h.network) for name, h in self._handles.items())
            for drive_cfg in config.drives:
                bus_cfg = config.bus(drive_cfg.bus)
                record, port = self.supervisor.port(drive_cfg.name)
                drive = Drive(drive_cfg, self._handles[drive_cfg.bus].network, ods[drive_cfg.name],
                              host_node_id=bus_cfg.host_node_id, sync_period_s=bus_cfg.sync_period_s,
                              record=record, port=port, host_beats=self._handles[drive_cfg.bus].beats_sent,
                              host_heartbeat_s=bus_cfg.host_heartbeat_s)
                drive.watch.set_remote_frames(carries_remote_frames(self._handles[drive_cfg.bus].bus))
                self.drives[drive_cfg.name] = drive
                self.supervisor.add(drive)
        except BaseException:
            self._close_buses()
            if self.recorder is not None:
                self.recorder.close()
            raise

    # ------------------------------------------------------------------ lifecycle
    def start(self, *, reset: bool = True, take_over: bool = False, look_s: float | None = None) -> MotorDriver:
        """Look for another master, boot every drive (buses in parallel), start SYNC and
        supervision; enable only drives configured with ``arm_on_start``.

        Before its first NMT command the driver listens two host-heartbeat periods (at least
        LOOK_MIN_S) on each bus: another live master (a heartbeat with this driver's host id,
        SYNC, NMT commands, RPDOs or SDO writes to its drives) makes it refuse with
        :class:`ForeignMasterError`, nothing sent, unless ``take_over``. ``look_s``: listen this
        long instead (the bench's ``--look``)."""
        try:
            self._look(take_over, look_s)
            self._start(reset, take_over)
        except BaseException:  # a failed or interrupted start leaves nothing armed or open
            self.close()
            raise
        return self

    def _look(self, take_over: bool, look_s: float | None = None) -> None:
        window = look_s if look_s is not None else max(look_window_s(b.host_heartbeat_s) for b in self.config.buses)
        since = time.monotonic()
        time.sleep(window)
        for name, handle in self._handles.items():
            evidence = handle.foreign.master_evidence(since - 1.0)
            if not evidence:
                continue
            if not take_over:
                raise other_master_error(f"bus {name}", evidence)
            logger.warning("bus %s: another master is live (%s); taking the bus over as told", name, evidence)

    def _start(self, reset: bool, take_over: bool) -> None:
        with ThreadPoolExecutor(max_workers=max(1, len(self.drives)),
                                thread_name_prefix="rovercan-boot") as pool:
            futures = [pool.submit(d.boot.boot, reset=reset) for d in self.drives.values()]
            for future in futures:
                future.result()
        for handle in self._handles.values():
            handle.start_sync()
            handle.worker.submit(lambda: None).result()  # its thread now, not at the first bus loss
        self.supervisor.start(take_over)
        for drive in self.drives.values():
            if drive.config.arm_on_start and not drive.channel.held:
                drive.enable()

    def hold_motion(self, reason: str) -> None:
        """From here on every drive refuses every motion (enable, recover, home, a mode switch, a
        move, a set-point, a tool's SDO write) with ``reason`` and sends nothing, until
        :meth:`allow_motion`; an operation under way ends at its next step. The stops are still
        taken; this sends none (the caller stops the drives: :meth:`safe_stop`)."""
        for drive in self.drives.values():
            drive.channel.hold(reason)

    @property
    def motion_held(self) -> str:
        """Why motion is held (:meth:`hold_motion`), or "" while it is taken."""
        return next((d.channel.held for d in self.drives.values() if d.channel.held), "")

    def allow_motion(self) -> None:
        """Motion taken again; nothing is enabled by it."""
        for drive in self.drives.values():
            drive.channel.allow()

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

    def one_write(self) -> AbstractContextManager[list[tuple[str, Exception]]]:
        """The RPDOs this thread sends inside go out in one write a bus at the end, where the bus is
        socketcand (:meth:`GuardedNetwork.each_one_write`: another thread's frame, or this thread's
        SDO, still follows what was handed over before it): the set-points of one message for several
        joints. The list yielded names, at the end, each bus that failed with its error (its frames
        not written: :class:`HeldFramesLost`, naming them; or the bus broken after the write)."""
        return GuardedNetwork.each_one_write(self._networks)

    @property
    def bus_lost(self) -> dict[str, bool]:
        """Each bus: lost (the supervisor's judgement, read)."""
        return {name: rt.lost for name, rt in self.supervisor.bus.bus_records.items()}

    def rejected(self, drive: Drive) -> Rejected | None:
        """The frames of ``drive`` a receive callback of its bus raised on (None: none)."""
        return self._handles[drive.config.bus].network.rejected(drive.node_id)

    def jobs_health(self) -> Health:
        """The supervisor's loop and the background jobs' unexpected failures, graded."""
        supervisor = self.supervisor
        return jobs_health(supervisor.faults.snapshot(), ended=supervisor.ended, alive=not supervisor.dead,
                           now=time.monotonic())

    def kernel_health(self, bus: str) -> tuple[KernelBusHealth | None, str]:
        """What the kernel says of ``bus`` (state, counters: a socketcan bus), or None and why."""
        return self.supervisor.bus.kernel_health(bus)

    # ------------------------------------------------------------------ shutdown
    def safe_stop(self, drives: Iterable[Drive] | None = None) -> list[str]:
        """The one safe stop, for every caller (this driver's close, the lifecycle node's
        deactivate, the /disarm service): each powered drive of ``drives`` (default: all)
        quick-stopped if Operation Enabled, then its voltage disabled (Switch On Disabled, no
        torque), whatever the others did. A drive lost after its boot gets one last stop it need
        not answer. Returns what was not confirmed, one line a drive (empty: every drive is safe).
        A drive whose stop raised anything (a bug included: logged with its trace and counted as a
        failed "stop" job, which /diagnostics says) never keeps the others from theirs."""
        return self.stop_report(drives).lines

    def stop_report(self, drives: Iterable[Drive] | None = None) -> StopReport:
        """:meth:`safe_stop`, with the lost drives among what was not confirmed told apart (a
        transition that fails on a stop nobody can confirm would fail for as long as the drive
        is unplugged: the lifecycle node's deactivate). Every drive's quick stop first, then each
        one's voltage disabled once it has braked: no drive waits for another's ramp, and none
        has its power cut mid-ramp (a real drive's shaft would coast from there)."""
        report = StopReport([], [])
        braking = [d for d in (self.drives.values() if drives is None else drives)
                   if self._stop_step(d, report, self._quick_stop_first)]
        deadline = time.monotonic() + BRAKE_WAIT_MAX_S  # every drive brakes at once: one bound for all
        for drive in braking:
            self._stop_step(drive, report, lambda d: self._off_once_braked(d, deadline))
        return report

    def _stop_step(self, drive: Drive, report: StopReport, step: Callable[[Drive], tuple[str, bool, bool]]) -> bool:
        """One step of a drive's safe stop; what it could not confirm in ``report``. True: the drive
        goes on to the next step. Whatever it raises (a bug too: logged with its trace, counted as a
        failed "stop" job) ends that drive's stop, never another's."""
        lost = more = False
        try:
            said, lost, more = step(drive)
        except MotorError as err:
            said = str(err)
            logger.error("safe stop: %s", err)
        except Exception as err:  # a fault of this driver's: the next drives are stopped all the same
            said = f"{drive.name}: its stop failed unexpectedly ({type(err).__name__}: {err}); see the log"
            self.supervisor.faults.failed("stop", f"safe stop of {drive.name}", err)  # logged, counted: /diagnostics
        if said:
            report.lines.append(said)
            if lost:
                report.lost.append(said)
        return more

    @staticmethod
    def _quick_stop_first(drive: Drive) -> tuple[str, bool, bool]:
        """A drive's first step: what was not confirmed ("" safe, or nothing to do), whether that is
        because it was lost, and whether its voltage is to be disabled next."""
        if drive.cache.lost and drive.cache.booted:
            drive.watch.lost_while_closing()  # unheard, maybe turning: one last stop it needs not answer
            return f"{drive.name}: lost; a last quick stop was sent, unanswered (check its power and CAN cable)", True, False
        if drive.cache.lost:  # its bus gone (the supervisor's _drive_gone), or heard again and configured anew
            return (f"{drive.name}: lost and not configured (its bus gone, or it is being configured again); no stop"
                    " could be sent or confirmed: it stops itself on its watch of this host (host_timeout_ms);"
                    " check the bus (its adapter, the cable, the server) and the drive's power"), True, False
        if not drive.cache.booted:  # being configured again: not enabled again after it
            drive.channel.stopped_unsent("a safe stop while it was configured again")
            return "", False, False
        if drive.cache.state == State.OPERATION_ENABLED:
            drive.quick_stop()
        return "", False, True

    @classmethod
    def _off_once_braked(cls, drive: Drive, deadline: float) -> tuple[str, bool, bool]:
        """A drive's second step: its voltage disabled once its quick stop has braked it (by
        ``deadline`` at the latest); a drive lost meanwhile gets the lost drive's stop instead."""
        if not drive.cache.lost and not drive.power.wait_braked(deadline):
            logger.warning("safe stop: %s is still braking (Quick Stop Active, no standstill said) at the stop's"
                           " bound; its voltage is disabled now, and its shaft may coast from there", drive.name)
        if drive.cache.lost:
            said, lost, _ = cls._quick_stop_first(drive)
            return said, lost, False
        drive.disable_voltage()
        return "", False, False

    def _unit_objects(self) -> dict[str, dict[tuple[int, int], int]]:
        """Each booted drive's unit objects as it reported them at its last boot (the flight
        recorder's writer thread reads them: each drive's dict is replaced whole by its boot)."""
        return {name: drive.boot.unit_objects for name, drive in list(self.drives.items()) if drive.boot.unit_objects}

    def close(self) -> None:
        """Quick stop + disable drives, stop SYNC, stop threads, close buses. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for drive in self.drives.values():
            drive.close()  # refuse new commands from here on; the stops of safe_stop are still taken
        # the host heartbeat goes on during the safe stop: no drive reacts to its loss yet
        teardown("driver close", (self.safe_stop, self.supervisor.stop, self._end_workers, self._release_host_watch,
                                  self._close_buses, self._close_recorder))

    def _end_workers(self) -> None:
        for handle in self._handles.values():
            handle.worker.shutdown(wait=True, cancel_futures=True)  # a re-boot under way ends first

    def _close_recorder(self) -> None:
        if self.recorder is not None:
            self.recorder.close()  # writes what is pending

    def _release_host_watch(self) -> None:
        for drive in self.drives.values():
            try:
                drive.watch.release_host_watch()
            except MotorError as err:
                logger.info("%s: host watch left armed (%s); the drive reports the host's silence", drive.name, err)

    def _close_buses(self) -> None:
        for handle in self._handles.values():
            handle.stop_sync()
        for handle in self._handles.values():
            handle.close()


# the names callers imported from here before the split (motor_driver.runtime.driver stays their door)
__all__ = ["CONNECT_TIMEOUT_S", "FOREIGN_HOLD_S", "HANDSHAKE_TIMEOUT_S", "OPEN_ATTEMPTS", "SUPERVISOR_PERIOD_S",
           "SYNC_RATE_WINDOW_S", "BusHandle", "BusStats", "ForeignTraffic", "MotorDriver", "carries_remote_frames",
           "is_kernel_bus", "look_for_master", "look_window_s", "open_bus", "other_master_error", "sync_daemon",
           "wait_for_server"]

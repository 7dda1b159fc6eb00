"""The CiA 402 power state machine of one drive: enable, the stops, recover, the mode switch.

Owner: command threads. ``_cw`` is written under ``_lock`` only, and ``_lock`` is held only to
decide and send a frame or two (at most ``COMMAND_LOCK_WAIT_S`` waited for it), never while
waiting for the drive. Operations that wait (enable, homing, recover, a mode switch, the stops)
mark the drive busy instead (``_busy``, ``_generation``, ``_preempted``, under ``_lock``):
commands meanwhile are refused at once; a stop preempts them, and its frame is always the last
the drive gets (its decision and its frame are one critical section).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from can_config.eds import has_object
from can_config.errors import CommandRejected, DriveStateError, DriveTimeoutError
from can_config.objects import OD, SUPPORTED_MODE_BIT, OperationMode, emcy_text
from motor_driver.cia402 import CW, FAULT_STATES, SW, Command, State, next_step_to_enable
from motor_driver.drive.constants import (
    COMMAND_LOCK_WAIT_S,
    ENABLED_CW_MASK,
    MODE_SWITCH_TIMEOUT_S,
    STATE_POLL_S,
    TORQUE_MODES,
    TRANSITION_TIMEOUT_S,
    VELOCITY_MODES,
)
from motor_driver.drive.frames import CommandFrames

logger = logging.getLogger(__name__)


class PowerStateMachine(CommandFrames):
    """Layer 3: the CiA 402 power state machine and the operation modes."""

    def _init_state(self) -> None:
        super()._init_state()
        self._busy: str | None = None  # the operation in progress (enable, home, a stop, ...)
        self._busy_owner: int | None = None  # its thread
        self._generation = 0  # counts operations: a preempted one notices
        self._preempted: tuple[int, str] = (0, "")  # operations older than this generation were stopped
        self._supported_modes: int | None = None  # 0x6502, read once per boot

    @property
    def busy(self) -> str | None:
        """The operation in progress (enable, home, a stop, ...), or None: commands are refused meanwhile."""
        return self._busy

    def _wait_state(self, wanted: set[State], timeout_s: float, doing: str, *,
                    fault_ok: bool = False, generation: int | None = None) -> State:
        deadline = time.monotonic() + timeout_s
        with self._status_event:
            while True:
                state = self.state
                if generation is not None:  # before the wanted state: a stop that landed meanwhile wins
                    self._check_not_preempted(generation, doing)
                if state in wanted:
                    return state
                if state in FAULT_STATES and not fault_ok:
                    raise self._fault_error(doing)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    hint = ""
                    if state == State.READY_TO_SWITCH_ON and not self.statusword & SW.VOLTAGE_ENABLED:
                        hint = " The drive reports no voltage: is STO low or the E-stop pressed?"
                    raise DriveTimeoutError(f"{self.name} (node {self.node_id}): {doing}: still in"
                                            f" {state.name} (statusword 0x{self.statusword:04X}) after"
                                            f" {timeout_s:g} s.{hint}", node_id=self.node_id,
                                            statusword=self.statusword)
                self._status_event.wait(min(remaining, 0.05))

    def _fault_error(self, doing: str) -> DriveStateError:
        emcy = self.last_emcy
        code = emcy.code if emcy is not None else None
        what = f"EMCY 0x{code:04X} {emcy_text(code)}" if code else "no EMCY received"
        return DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is in FAULT"
                               f" ({what}); call recover() to reset it", node_id=self.node_id,
                               statusword=self.statusword, error_code=code)

    @contextmanager
    def _operation(self, name: str, *, preempt: bool = False) -> Iterator[int]:
        """A state-machine operation that waits for the drive (enable, homing, a stop): the drive
        is marked busy with it instead of its lock being held while it waits, so a command
        meanwhile is refused at once (never queued behind seconds of waiting). ``preempt``:
        a stop, which does not wait for anyone; the operation it interrupts ends with an error.
        Yields the operation's generation (see :meth:`_check_not_preempted`)."""
        me = threading.get_ident()
        with self._lock:
            if self._busy and self._busy_owner != me and not preempt:
                raise CommandRejected(f"{self.name}: {name} refused: the drive is busy with {self._busy};"
                                      " nothing was sent. Try again when it is done.")
            outer = (self._busy, self._busy_owner)
            self._busy, self._busy_owner = name, me
            self._generation += 1
            generation = self._generation
            if preempt:
                self._preempted = (generation, name)  # every operation started before this one ends
        if preempt:
            with self._status_event:
                self._status_event.notify_all()  # an operation waiting for the drive notices at once
        try:
            yield generation
        finally:
            with self._lock:
                if self._busy_owner == me:
                    self._busy, self._busy_owner = outer

    def _check_not_preempted(self, generation: int, doing: str) -> None:
        if self.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver shut down meanwhile",
                                  node_id=self.node_id)
        before, by = self._preempted
        if generation < before:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} interrupted by {by}",
                                  node_id=self.node_id)

    @contextmanager
    def _command(self, name: str) -> Iterator[None]:
        """A command of a frame or two: the lock for at most COMMAND_LOCK_WAIT_S, and refused at
        once while an operation runs, so that a topic callback never waits on a service."""
        if not self._lock.acquire(timeout=COMMAND_LOCK_WAIT_S):
            raise CommandRejected(f"{self.name}: {name} refused: another command holds the drive;"
                                  " nothing was sent")
        try:
            self._refuse_if_busy(name)
            yield
        finally:
            self._lock.release()

    def _refuse_if_busy(self, doing: str) -> None:
        if self._busy and self._busy_owner != threading.get_ident():
            raise CommandRejected(f"{self.name}: {doing} refused: the drive is busy with {self._busy};"
                                  " nothing was sent. Send it again when that is done.")

    def _require_usable(self, doing: str) -> None:
        if self.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver is shut down;"
                                  " nothing was sent", node_id=self.node_id)
        if self.lost:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is lost (no"
                                  " heartbeat); nothing was sent", node_id=self.node_id)
        if self.foreign_master:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} refused: the drive is not under"
                                  f" this driver's control: another master is on the bus ({self.foreign_master})."
                                  " Stop the other driver or bench tool; this one configures the drive again"
                                  " (not enabled) once the bus is its own. Nothing was sent.", node_id=self.node_id)
        if not self.booted:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is not"
                                  " booted (boot() it, or wait for re-configuration after a reset)",
                                  node_id=self.node_id)

    def _require_resolution(self, doing: str) -> None:
        """Motion needs the position resolution from the config or the drive, never an assumption."""
        if not self.scale.resolution_known:
            raise CommandRejected(f"{self.name} (node {self.node_id}): {doing} refused: the position resolution is"
                                  " unknown (no counts_per_rev in the config, no 0x608F or 0x60A8 on the drive), so"
                                  " degrees cannot be turned into the drive's units. Set counts_per_rev for this drive"
                                  " (bench: --counts-per-rev N). Nothing was sent.")

    def enable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Walk the state machine to Operation Enabled (transitions 2, 3, 4), holding position.

        Refused for a drive that cannot watch the host (no 0x1016), unless the config allows it.
        A stop (quick stop, disable, the driver's close) preempts it.
        """
        with self._operation("enable") as generation:
            self._require_usable("enable")
            self.fault_seen = None  # asked again: from here on a FAULT stops motion anew
            self._handshake.reset()  # a drive that left Operation Enabled acknowledges nothing more
            if self.host_watch is None and not self.config.allow_no_host_watch:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused: {self.host_watch_problem},"
                                      " so it would keep moving if this process were killed, hung or lost power."
                                      " Give it a heartbeat consumer, or set allow_no_host_watch: true for this"
                                      " drive (bench: --allow-no-host-watch) to arm it anyway. Nothing was sent.")
            self._target_counts = self.position_counts
            if self.state != State.OPERATION_ENABLED:
                self._clear_held_target()
            for _ in range(6):
                state = self.state
                if state == State.OPERATION_ENABLED:
                    if self._cw & ENABLED_CW_MASK != ENABLED_CW_MASK:  # enabled, but not by this driver's word
                        self._transition(generation, "enable", Command.ENABLE_OPERATION)
                    break
                if state in FAULT_STATES:
                    raise self._fault_error("enable")
                step = next_step_to_enable(state)
                if step is None:
                    self._wait_state({State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                                      State.SWITCHED_ON, State.OPERATION_ENABLED}, timeout_s, "enable",
                                     generation=generation)
                    continue
                target, number, command = step
                logger.debug("node %d: transition %d to %s", self.node_id, number, target.name)
                self._hook(f"enable: before transition {number}")
                self._transition(generation, f"enable (transition {number} to {target.name})", command)
                self._hook(f"enable: sent transition {number}")
                self._wait_state({target, State.OPERATION_ENABLED}, timeout_s,
                                 f"enable (transition {number} to {target.name})", generation=generation)
            with self._lock:  # the verdict and a stop are ordered too
                self._check_not_preempted(generation, "enable")
                if self.state != State.OPERATION_ENABLED:
                    raise DriveTimeoutError(f"{self.name}: could not reach OPERATION_ENABLED",
                                            node_id=self.node_id, statusword=self.statusword)
                self.was_enabled = True

    def _transition(self, generation: int, doing: str, command: Command | int, edge: int = 0) -> None:
        """One controlword of an operation (enable, recover, homing): the check that no stop came
        since the operation began and the frame are one critical section, so a stop's frame is
        always the last the drive gets."""
        with self._lock:
            self._check_not_preempted(generation, doing)
            self._cw = int(command)
            if self._cw & ENABLED_CW_MASK == ENABLED_CW_MASK:
                self._enable_sent_at = time.monotonic()
            self._send_cw(self._cw | edge)

    def _clear_held_target(self) -> None:
        """Before enabling: the drive still holds the last target from before a fault or a stop
        and follows it the moment it reaches Operation Enabled. Velocity and torque modes: a
        recovered wheel ran at its old 0x60FF (286 deg/s) until the watchdog; so 0 here. The
        cyclic position modes: a wheel stopped at speed brakes on past its last set-point
        (0x607A / 0x60C1:1) and jumped back to it (9 deg); so where the shaft is now (0x6064,
        read now: the braked shaft does not move). By SDO: the RPDO that carries the target
        also carries the controlword "enable operation"."""
        mode = self.mode_display
        if mode in VELOCITY_MODES:
            self._write_typed(OD.TARGET_VELOCITY, 0, 0)
        elif mode in TORQUE_MODES:
            self._write_typed(OD.TARGET_TORQUE, 0, 0)
        elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            actual = self._read_int(OD.POSITION_ACTUAL, 0)
            if actual is None:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused in"
                                      f" {OperationMode(mode).name}: the drive's EDS has no 0x6064, so its held"
                                      " set-point cannot be moved to where the shaft is. Nothing was sent.")
            self._target_counts = actual
            index, sub = (OD.TARGET_POSITION, 0) if mode == OperationMode.CYCLIC_SYNC_POSITION else \
                (OD.INTERPOLATION_DATA, 1)
            if has_object(self.od, index, sub):  # without it, nothing is held
                self._write_typed(index, sub, actual)

    def _stop(self, name: str, command: Command, wanted: set[State], timeout_s: float) -> None:
        """A stop: it preempts every operation under way, and its decision and its frame are one
        critical section (:meth:`_stop_frame`); the frame is always sent, since the state last
        seen may be stale while another frame is on its way. Then it waits for ``wanted`` (or a
        fault) without holding the lock."""
        with self._operation(name, preempt=True):
            self._stop_frame(command, name)
            self._hook(f"{name}: sent")
            self._wait_state(wanted | FAULT_STATES, timeout_s, name)

    def _stop_frame(self, command: Command, by: str) -> None:
        """The frame of a stop, decided and sent under the lock: no command or transition can
        follow it unless it was decided after it. The set-point handshake is forgotten first, so
        the receive thread sends no "enable operation" reply after it."""
        with self._lock:
            self._generation += 1
            self._preempted = (self._generation, by)
            self.was_enabled = False
            self.velocity_commanded = False
            self._handshake.reset()
            self._cw = int(command)
            self._send_cw(self._cw)

    def disable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Shutdown (transition 8, 6 or 2): power stage off, drive in Ready to Switch On."""
        self._stop("disable", Command.SHUTDOWN, {State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED}, timeout_s)

    def quick_stop(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Quick stop (transition 11; 7 or 10 from the states before): the drive brakes on its
        quick-stop ramp."""
        self._stop("quick stop", Command.QUICK_STOP, {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED}, timeout_s)

    def disable_voltage(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Disable voltage (transitions 7, 9, 10, 12): power stage off, Switch On Disabled."""
        self._stop("disable voltage", Command.DISABLE_VOLTAGE, {State.SWITCH_ON_DISABLED}, timeout_s)

    def halt(self, on: bool = True) -> None:
        """Set or clear the halt bit (8): stop on the profile deceleration, stay enabled."""
        with self._command("halt"):
            self._require_usable("halt")
            self._cw = (self._cw | CW.HALT) if on else (self._cw & ~CW.HALT)
            self._send_cw(self._cw)

    def recover(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Fault reset (transition 15), then back to the enable state the drive had before."""
        with self._operation("recover") as generation:
            self._require_usable("recover")
            restore = self.was_enabled
            if self.state in FAULT_STATES:
                if self.state == State.FAULT_REACTION_ACTIVE:
                    self._wait_state({State.FAULT}, timeout_s, "recover (fault reaction)", fault_ok=True,
                                     generation=generation)
                self._transition(generation, "recover", 0)
                self._transition(generation, "recover", Command.FAULT_RESET)
                self._wait_state({State.SWITCH_ON_DISABLED}, timeout_s, "fault reset (transition 15)",
                                 fault_ok=True, generation=generation)
                self._transition(generation, "recover", 0)
            self.last_emcy = None
            self.fault_seen = None
            if restore:
                self.enable(timeout_s)

    def supported_modes(self) -> int:
        """0x6502 as the drive reports it (read by SDO once per boot; all modes without it)."""
        if self._supported_modes is None:
            if not has_object(self.od, OD.SUPPORTED_DRIVE_MODES):
                self._supported_modes = 0xFFFF_FFFF
            else:
                self._supported_modes = int(self.sdo_read_value(OD.SUPPORTED_DRIVE_MODES))  # type: ignore[arg-type]
        return self._supported_modes

    def _switch_mode_sdo(self, mode: OperationMode, generation: int | None = None) -> None:
        """0x6060 by SDO, then 0x6061 polled until it shows ``mode``. No lock is held: the caller
        marked the drive busy; a stop meanwhile preempts it (``generation``)."""
        if generation is not None:
            with self._lock:
                self._check_not_preempted(generation, f"mode switch to {mode.name}")
                self._target_counts = self.position_counts
                self._handshake.reset()
        self._write_typed(OD.MODES_OF_OPERATION, 0, int(mode))
        self._hook("mode switch: 0x6060 written")
        deadline = time.monotonic() + MODE_SWITCH_TIMEOUT_S
        while True:
            shown = int(self.sdo_read_value(OD.MODES_OF_OPERATION_DISPLAY))  # type: ignore[arg-type]
            if generation is not None:
                self._check_not_preempted(generation, f"mode switch to {mode.name}")
            if shown == mode:
                self.mode_display = shown
                return
            if time.monotonic() > deadline:
                raise DriveTimeoutError(f"node {self.node_id}: mode {mode.name} written to 0x6060 but"
                                        f" 0x6061 still shows {shown} after {MODE_SWITCH_TIMEOUT_S:g} s",
                                        node_id=self.node_id, statusword=self.statusword)
            time.sleep(STATE_POLL_S)

    def set_mode(self, mode: OperationMode | int) -> None:
        """Switch the mode of operation; refuses modes 0x6502 does not list; waits for 0x6061.
        The drive is busy meanwhile (commands refused at once, a stop preempts it); no lock is
        held across its SDO round trips."""
        mode = OperationMode(mode)
        bit = SUPPORTED_MODE_BIT.get(mode)
        supported = self.supported_modes()
        if bit is None or not supported >> bit & 1:
            raise CommandRejected(f"{self.name}: mode {mode.name} is not supported by node"
                                  f" {self.node_id} (0x6502 = 0x{supported:08X}); supported:"
                                  f" {', '.join(m.name for m, b in SUPPORTED_MODE_BIT.items() if supported >> b & 1)}")
        if self.mode_display == mode:
            return
        with self._operation("mode switch") as generation:
            self._switch_mode_sdo(mode, generation)

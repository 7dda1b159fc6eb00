"""Motion commands, one family per operation mode: profile position (with the set-point
handshake), profile velocity and torque, the cyclic synchronous modes and interpolated position.

Threads: command threads (the API, ROS callbacks). Each command checks its input (finite, in
the joint's limits, resolution known) before anything is sent, then decides and sends its frame
under ``_lock`` in one step (:meth:`Motion._require_motion`); ``_stream_velocity_counts_s`` is
written there only.
"""

from __future__ import annotations

import logging
import time

from can_config.errors import CommandRejected, DriveStateError, DriveTimeoutError
from can_config.objects import OD, SUPPORTED_MODE_BIT, OperationMode
from motor_driver.cia402 import CW, FAULT_STATES, SW, Command, State
from motor_driver.drive.constants import CONTINUOUS_COMMAND_LIMIT_DEG, ENABLED_CW_MASK
from motor_driver.drive.limits import LimitGuard
from motor_driver.pdo import encode_rpdo
from motor_driver.units import check_counts, check_limits, nearest_equivalent, require_finite

logger = logging.getLogger(__name__)


class Motion(LimitGuard):
    """Layer 5: motion commands, one family per operation mode, limits checked on each."""

    def _init_state(self) -> None:
        super()._init_state()
        self._stream_velocity_counts_s = 0  # the last CSV target (command threads, under _lock)
        self.turns_offset_deg = 0.0

    def _position_target_counts(self, angle_deg: float) -> int:
        angle = require_finite(f"{self.name} angle", angle_deg, "deg")
        self._require_resolution("a position command")
        cfg = self.config
        if cfg.is_continuous:
            if abs(angle) > CONTINUOUS_COMMAND_LIMIT_DEG:
                raise CommandRejected(f"{self.name}: {angle:g} deg: a continuous joint takes an angle from"
                                      f" -{CONTINUOUS_COMMAND_LIMIT_DEG:g} to {CONTINUOUS_COMMAND_LIMIT_DEG:g} deg"
                                      " and moves the short way to it. Nothing was sent.")
            angle = nearest_equivalent(angle, self.angle_deg)
        else:
            check_limits(self.name, angle, cfg.min_deg, cfg.max_deg)
        return check_counts(self.name, self.scale.deg_to_counts(angle), "target position")

    def check_position(self, angle_deg: float) -> float:
        """The (multi-turn) angle a position command of ``angle_deg`` would go to, or
        :class:`CommandRejected` naming the limit; nothing is sent."""
        return self.scale.counts_to_deg(self._position_target_counts(angle_deg))

    def move_to(self, angle_deg: float, *, wait: bool = False, timeout_s: float | None = None) -> float:
        """Profile-position move to ``angle_deg``; returns the (multi-turn) target in degrees.

        A continuous joint takes the short way round; a limited joint refuses targets beyond
        its limits. Nothing is sent for a refused command.
        """
        counts = self._position_target_counts(angle_deg)
        self._ensure_mode(OperationMode.PROFILE_POSITION, "move")
        if self.plan.rpdo_with(OD.CONTROLWORD) is None:
            raise CommandRejected(f"{self.name} (node {self.node_id}): move refused: the controlword cannot be"
                                  " PDO-mapped on this drive, and the set-point handshake's replies come from the"
                                  " receive thread, which never waits for an SDO. Nothing was sent.")
        if self.plan.rpdo_with(OD.TARGET_POSITION) is None:
            # 0x607A only by SDO (the SCHUNK PRL120): written here, on the caller's thread and with
            # the drive busy (no lock held while the SDO waits); the handshake sends only the edge
            with self._operation("move (target by SDO)"):
                self._write_typed(OD.TARGET_POSITION, 0, counts)
                with self._lock:
                    self._require_motion(OperationMode.PROFILE_POSITION, "move")
                    self._cw &= ~CW.HALT
                    self._handshake.command(counts)
        else:
            with self._command("move"):
                self._require_motion(OperationMode.PROFILE_POSITION, "move")
                self._cw &= ~CW.HALT
                self._handshake.command(counts)
        if wait:
            self.wait_target_reached(timeout_s)
        return self.scale.counts_to_deg(counts)

    def wait_target_reached(self, timeout_s: float | None = None) -> None:
        if timeout_s is None:
            span = self.scale.span_deg(self._target_counts - self.position_counts)
            cfg = self.config
            timeout_s = 2.0 + span / cfg.profile_velocity_deg_s + 2 * cfg.profile_velocity_deg_s / cfg.profile_acceleration_deg_s2
        deadline = time.monotonic() + timeout_s
        with self._status_event:
            while True:
                if self.state in FAULT_STATES:
                    raise self._fault_error("move")
                if self._handshake.idle and self.statusword & SW.TARGET_REACHED:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DriveTimeoutError(f"{self.name}: target not reached within {timeout_s:.1f} s"
                                            f" (at {self.angle_deg:.2f} deg, target"
                                            f" {self.scale.counts_to_deg(self._target_counts):.2f} deg)",
                                            node_id=self.node_id, statusword=self.statusword)
                self._status_event.wait(min(remaining, 0.05))
        # the statusword comes on change, the position on SYNC: wait for a position sampled
        # after the drive said 'reached', so the caller's snapshot is not one period old
        seq = self._position_seq
        settle = time.monotonic() + 3 * self.sync_period_s + 0.05
        while self._position_seq == seq and time.monotonic() < settle:
            time.sleep(0.001)

    def set_profile_velocity(self, velocity_deg_s: float) -> None:
        """The speed of the following profile-position moves (0x6081), at most max_velocity_deg_s."""
        speed = require_finite(f"{self.name} profile velocity", velocity_deg_s, "deg/s")
        self._require_resolution("a profile velocity")
        if not 0 < speed <= self.config.max_velocity_deg_s:
            raise CommandRejected(f"{self.name}: profile velocity {speed:g} deg/s: allowed 0 < speed <="
                                  f" {self.config.max_velocity_deg_s:g} (max_velocity_deg_s). Nothing was sent.")
        with self._operation("profile velocity"):  # an SDO round trip: busy, not the lock
            self._write_typed(OD.PROFILE_VELOCITY, 0, self.scale.magnitude_to_drive(speed))

    def set_velocity(self, velocity_deg_s: float) -> None:
        """Profile-velocity command in deg/s, limited by max_velocity_deg_s; feeds the watchdog."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.PROFILE_VELOCITY, "velocity command")
        with self._command("velocity command"):
            self._refuse_past_limit(velocity, abs(velocity), self.config.profile_acceleration_deg_s2,
                                    f"velocity {velocity:g} deg/s")
            self._require_motion(OperationMode.PROFILE_VELOCITY, "velocity command")
            self._send_velocity(counts_s)
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = velocity != 0.0

    def _require_enabled(self, doing: str) -> None:
        self._require_usable(doing)
        if self.fault_seen is not None and self.state not in FAULT_STATES:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} refused: the drive reported FAULT"
                                  f" (statusword 0x{self.fault_seen:04X}) since it was enabled, though it shows"
                                  f" {self.state.name} now; recover() and enable() it again",
                                  node_id=self.node_id, statusword=self.statusword)
        if self.state != State.OPERATION_ENABLED or self._cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
            if self.state in FAULT_STATES:
                raise self._fault_error(doing)
            shown = self.state.name if self.state != State.OPERATION_ENABLED else "stopping"
            raise DriveStateError(f"{self.name}: {doing} refused: the drive is {shown}; enable() it"
                                  " first", node_id=self.node_id, statusword=self.statusword)

    def _ensure_mode(self, mode: OperationMode, doing: str) -> None:
        """Before a motion command, without the lock: the drive enabled and in ``mode`` (a mode
        switch is an operation of its own, :meth:`set_mode`)."""
        self._refuse_if_busy(doing)
        self._require_enabled(doing)
        if self.mode_display != mode:
            self.set_mode(mode)

    def _require_motion(self, mode: OperationMode, doing: str) -> None:
        """Under the lock, right before a motion frame, decided with it as one step: the drive is
        usable, this driver's last controlword was Enable Operation (no stop since), the last
        statusword said Operation Enabled, and the mode is still ``mode``."""
        self._require_enabled(doing)
        if self.mode_display != mode:
            raise CommandRejected(f"{self.name}: {doing} refused: the drive left {mode.name} meanwhile (now"
                                  f" {self.mode_display}); nothing was sent. Send it again.")

    def _checked_torque(self, torque_nm: float) -> float:
        torque = require_finite(f"{self.name} torque", torque_nm, "Nm")
        self._require_resolution("a torque command")  # its limit guard works in degrees
        limit = self.config.max_torque_nm or self.scale.rated_torque_nm * self.scale.gear_ratio
        if abs(torque) > limit:
            raise CommandRejected(f"{self.name}: torque {torque:g} Nm is beyond the limit max_torque_nm={limit:g}"
                                  f" (allowed -{limit:g} to {limit:g} Nm). Nothing was sent.")
        return torque

    def _checked_velocity(self, velocity_deg_s: float) -> tuple[float, int]:
        velocity = require_finite(f"{self.name} velocity", velocity_deg_s, "deg/s")
        self._require_resolution("a velocity command")
        vmax = self.config.max_velocity_deg_s
        if abs(velocity) > vmax:
            raise CommandRejected(f"{self.name}: velocity {velocity:g} deg/s is beyond the limit"
                                  f" max_velocity_deg_s={vmax:g} (allowed -{vmax:g} to {vmax:g}). Nothing"
                                  " was sent.")
        return velocity, check_counts(self.name, self.scale.deg_s_to_counts_s(velocity), "velocity")

    def _torque_command(self, torque_nm: float, mode: OperationMode, doing: str, what: str) -> None:
        """A torque target in ``mode`` (profile or cyclic torque): checked, limit-guarded, sent."""
        torque = self._checked_torque(torque_nm)
        self._ensure_mode(mode, doing)
        with self._command(doing):
            self._refuse_past_limit(torque, 0.0, self.config.quick_stop_decel_deg_s2, f"{what} {torque:g} Nm",
                                    torque_mode=True)
            self._require_motion(mode, doing)
            self._send_torque(self.scale.nm_to_permille(torque))
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = torque != 0.0

    def set_torque(self, torque_nm: float) -> None:
        """Profile-torque command in Nm at the joint, limited by max_torque_nm; feeds the watchdog."""
        self._torque_command(torque_nm, OperationMode.PROFILE_TORQUE, "torque command", "torque")

    def stream_velocity(self, velocity_deg_s: float) -> None:
        """Cyclic synchronous velocity (CSV): one target per SYNC period, which the drive takes
        at the next SYNC without a ramp of its own (the caller's stream is the ramp). Limited by
        max_velocity_deg_s; speeding up by more than the quick-stop deceleration over two SYNC
        periods in one step is refused (slowing down never is); feeds the watchdog. Refused on a
        drive whose 0x6502 does not list CSV."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point")
        with self._command("CSV set-point"):
            self._refuse_past_limit(velocity, abs(velocity), self.config.quick_stop_decel_deg_s2,
                                    f"CSV velocity {velocity:g} deg/s")
            self._require_motion(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point")
            previous = self.scale.counts_s_to_deg_s(self._stream_velocity_counts_s) if self.velocity_commanded else 0.0
            max_step = self.config.quick_stop_decel_deg_s2 * 2 * self.sync_period_s
            if abs(velocity) > abs(previous) and abs(velocity - previous) > max_step:
                raise CommandRejected(f"{self.name}: CSV set-point {velocity:g} deg/s jumps"
                                      f" {abs(velocity - previous):.1f} deg/s from the last one ({previous:g});"
                                      f" at most {max_step:.1f} deg/s per step speeding up (the quick-stop"
                                      " deceleration over two SYNC periods). Ramp it. Nothing was sent.")
            self._send_velocity(counts_s)
            self._stream_velocity_counts_s = counts_s
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = velocity != 0.0

    def stream_torque(self, torque_nm: float) -> None:
        """Cyclic synchronous torque (CST): one torque target in Nm at the joint per SYNC period,
        limited by max_torque_nm; feeds the watchdog (which sends zero torque). Refused on a
        drive whose 0x6502 does not list CST."""
        self._torque_command(torque_nm, OperationMode.CYCLIC_SYNC_TORQUE, "CST set-point", "CST torque")

    def command_velocity(self, velocity_deg_s: float) -> None:
        """A velocity command in the drive's configured way: profile velocity, or CSV
        (``velocity_mode: cyclic``)."""
        if self.config.velocity_mode == "cyclic":
            self.stream_velocity(velocity_deg_s)
        else:
            self.set_velocity(velocity_deg_s)

    def command_torque(self, torque_nm: float) -> None:
        """A torque command in the drive's configured way: profile torque, or CST
        (``torque_mode: cyclic``)."""
        if self.config.torque_mode == "cyclic":
            self.stream_torque(torque_nm)
        else:
            self.set_torque(torque_nm)

    def stream_position(self, angle_deg: float, *, max_step_deg: float | None = None) -> None:
        """One position set-point per SYNC period, no handshake: cyclic synchronous position,
        or interpolated position (0x60C1:1, controlword bit 4 "enable ip mode") on a drive
        whose 0x6502 lists IP but not CSP (the SCHUNK PRL120 is one).

        Refuses a setpoint that jumps further than ``max_step_deg`` (default: max velocity
        over two SYNC periods) from the previous one: a streamed trajectory must be smooth.
        """
        counts = self._position_target_counts(angle_deg)
        mode = self._streaming_mode()
        doing = "CSP setpoint" if mode == OperationMode.CYCLIC_SYNC_POSITION else "IP setpoint"
        self._ensure_mode(mode, doing)
        with self._command("set-point"):
            self._require_motion(mode, doing)
            if max_step_deg is None:
                max_step_deg = self.config.max_velocity_deg_s * 2 * self.sync_period_s
            step = self.scale.span_deg(counts - self._target_counts)
            if step > max_step_deg:
                raise CommandRejected(f"{self.name}: CSP setpoint jumps {step:.3f} deg from the last one; at most"
                                      f" {max_step_deg:.3f} deg per step (max_velocity_deg_s over two SYNC"
                                      " periods) is allowed. Nothing was sent.")
            self._target_counts = counts
            cw = int(Command.ENABLE_OPERATION)
            target = OD.TARGET_POSITION
            if mode == OperationMode.INTERPOLATED_POSITION:
                cw |= CW.NEW_SETPOINT  # enable ip mode: the drive follows 0x60C1:1 at each SYNC
                target = OD.INTERPOLATION_DATA
            pdo = self.plan.rpdo_with(target)
            if pdo is not None:
                self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw, target: counts}))
            else:
                self._write_typed(target, 1 if target == OD.INTERPOLATION_DATA else 0, counts)
                self._send_cw(cw)

    def _streaming_mode(self) -> OperationMode:
        if self.mode_display in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            return OperationMode(self.mode_display)  # the hot path: streaming already
        supported = self.supported_modes()
        for mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            if supported >> SUPPORTED_MODE_BIT[mode] & 1:
                return mode
        raise CommandRejected(f"{self.name}: streaming set-points needs cyclic synchronous or interpolated"
                              f" position; node {self.node_id} supports neither (0x6502 = 0x{supported:08X}).")

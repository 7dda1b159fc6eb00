"""Limits on every velocity and torque path: the stopping-distance guard and the watchdog.

Threads: command threads check a command against the limit under ``_lock`` before its frame;
the supervisor brakes a joint whose stopping distance reached its limit (``guard_limits``) and
zeroes a velocity command that was not renewed (``stop_velocity``); it never waits for the
lock (a command holding it is checked itself; the next period tries again).
"""

from __future__ import annotations

import logging
import time

from can_config.errors import CommandRejected
from motor_driver.cia402 import Command, State
from motor_driver.drive.constants import LIMIT_ACCEL_MARGIN_S, LIMIT_MARGIN_S, MAX_EXTRAPOLATION_S, TORQUE_MODES, VELOCITY_MODES
from motor_driver.drive.power import PowerStateMachine

logger = logging.getLogger(__name__)


class LimitGuard(PowerStateMachine):
    """Layer 4: the limit guard and the velocity watchdog, for every velocity and torque path."""

    def _init_state(self) -> None:
        super()._init_state()
        self.limit_stops = 0  # brakes by the limit guard (command threads and the supervisor, under _lock)
        self.watchdog_stops = 0  # zero commands sent by the watchdog (the supervisor, under _lock)

    def _limit_ahead(self, direction: float, speed_deg_s: float, decel_deg_s2: float,
                     torque_mode: bool = False) -> str | None:
        """The limit a motion in ``direction`` at ``speed_deg_s`` (or the joint's own speed, if
        higher) could not stop before when braking at ``decel_deg_s2``; None when clear.
        ``torque_mode``: nothing caps the joint's acceleration (a profile does in the velocity
        modes), so it speeds up on its measured acceleration while the guard reacts."""
        cfg = self.config
        if cfg.is_continuous or direction == 0 or cfg.min_deg is None or cfg.max_deg is None:
            return None
        velocity = self.scale.counts_s_to_deg_s(self.velocity_counts_s)
        accel = self.scale.counts_s_to_deg_s(self.accel_counts_s2) if torque_mode else 0.0
        accel = accel if accel * direction > 0 else 0.0  # only speeding up toward the limit counts
        age = min(max(time.time() - self.stamp, 0.0), MAX_EXTRAPOLATION_S) if self.stamp else 0.0
        # where the joint is now, and how fast, not when its TPDO was sampled
        angle = self.angle_deg + velocity * age + 0.5 * accel * age * age
        speed = max(speed_deg_s, abs(velocity + accel * age))
        gain = abs(accel) * LIMIT_ACCEL_MARGIN_S  # speed gained before the brake takes hold
        need = (speed + gain) ** 2 / (2 * decel_deg_s2) + speed * LIMIT_MARGIN_S + 0.5 * gain * LIMIT_ACCEL_MARGIN_S
        if direction > 0 and cfg.max_deg - angle <= need:
            return f"max_deg={cfg.max_deg:g}"
        if direction < 0 and angle - cfg.min_deg <= need:
            return f"min_deg={cfg.min_deg:g}"
        return None

    def _refuse_past_limit(self, direction: float, speed_deg_s: float, decel_deg_s2: float, what: str,
                           torque_mode: bool = False) -> None:
        limit = self._limit_ahead(direction, speed_deg_s, decel_deg_s2, torque_mode)
        if limit is None:
            return
        self._brake()
        raise CommandRejected(f"{self.name}: {what} refused: at {self.angle_deg:.2f} deg the joint could not stop"
                              f" before its limit {limit} braking at {decel_deg_s2:g} deg/s^2; it is stopping."
                              " Command away from the limit, or move_to() a target inside it.")

    def _brake(self) -> None:
        """Stop a velocity- or torque-commanded joint at once, without waiting: zero velocity
        (the drive brakes on its profile deceleration) or, in torque mode, a quick stop."""
        self.velocity_commanded = False
        if self.state != State.OPERATION_ENABLED:
            return
        self.limit_stops += 1
        if self.mode_display in VELOCITY_MODES:
            self._send_velocity(0)
        elif self.mode_display in TORQUE_MODES:
            self._send_torque(0)
            self._stop_frame(Command.QUICK_STOP, "the limit guard's quick stop")

    def guard_limits(self) -> None:
        """Supervisor, every period: brake a velocity- or torque-commanded limited joint whose
        stopping distance has reached its limit (the drive's own 0x607D is the backstop)."""
        if self.config.is_continuous or not self.velocity_commanded:
            return
        velocity = self.scale.counts_s_to_deg_s(self.velocity_counts_s)
        torque_mode = self.mode_display in TORQUE_MODES
        decel = self.config.quick_stop_decel_deg_s2 if torque_mode else self.config.profile_acceleration_deg_s2
        limit = self._limit_ahead(velocity, abs(velocity), decel, torque_mode)
        if limit is None:
            return
        # never waits (the supervisor's period is the host heartbeat's): a command that holds the
        # lock is checked against the limit itself, and the next period brakes if it still must
        if not self._lock.acquire(blocking=False):
            return
        try:
            logger.warning("%s: at %.2f deg moving %.1f deg/s toward its limit %s; braking", self.name,
                           self.angle_deg, velocity, limit)
            self._brake()
        finally:
            self._lock.release()

    def stop_velocity(self) -> bool:
        """Watchdog action: zero velocity (PV) or zero torque (PT). Never waits: when a command
        holds the drive (enable, homing, a mode switch: each ends the velocity command itself),
        it returns False and the supervisor tries again at its next period."""
        if not self._lock.acquire(blocking=False):
            return False
        try:
            if self._busy:
                return False
            self.velocity_commanded = False
            if self.state != State.OPERATION_ENABLED:
                return True
            if self.mode_display in VELOCITY_MODES:
                self._send_velocity(0)
                self.watchdog_stops += 1
            elif self.mode_display in TORQUE_MODES:
                self._send_torque(0)
                self.watchdog_stops += 1
            return True
        finally:
            self._lock.release()

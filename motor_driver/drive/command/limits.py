"""Limits on every velocity and torque path: the stopping-distance guard and the watchdog.

Owner: this object's counters (``limit_stops``, ``watchdog_stops``), written by whoever brakes,
always while holding the command channel (its frames). Command threads check a command against
the limit inside the channel's command, with its frame; the supervisor brakes a joint whose
stopping distance reached its limit (:meth:`guard_limits`) and zeroes a velocity command that
was not renewed (:meth:`stop_velocity`); it never waits for the channel (a command holding it
is checked itself; the next period tries again). A brake goes out only while this driver's
last controlword was Enable Operation (the channel checks it): never after a stop.
"""

from __future__ import annotations

import logging
import time

from can_config.config import DriveConfig
from can_config.errors import CommandRejected
from motor_driver.drive.command.channel import CommandChannel, LockedCommand
from motor_driver.drive.constants import LIMIT_ACCEL_MARGIN_S, LIMIT_MARGIN_S, MAX_EXTRAPOLATION_S, TORQUE_MODES, VELOCITY_MODES
from motor_driver.drive.received.state import DriveCache
from motor_driver.protocol.cia402 import Command, State

logger = logging.getLogger(__name__)


class LimitGuard:
    """The limit guard and the velocity watchdog of one drive."""

    def __init__(self, config: DriveConfig, cache: DriveCache, channel: CommandChannel) -> None:
        self.config, self._cache, self._channel = config, cache, channel
        self.name, self.node_id = config.name, config.node_id
        self.limit_stops = 0
        self.watchdog_stops = 0

    def limit_ahead(self, direction: float, speed_deg_s: float, decel_deg_s2: float,
                    torque_mode: bool = False) -> str | None:
        """The limit a motion in ``direction`` at ``speed_deg_s`` (or the joint's own speed, if
        higher) could not stop before when braking at ``decel_deg_s2``; None when clear.
        ``torque_mode``: nothing caps the joint's acceleration (a profile does in the velocity
        modes), so it speeds up on its measured acceleration while the guard reacts."""
        cfg = self.config
        if cfg.is_continuous or direction == 0 or cfg.min_deg is None or cfg.max_deg is None:
            return None
        cache = self._cache
        rx = cache.received
        scale = cache.scale
        velocity = scale.counts_s_to_deg_s(rx.velocity_counts_s)
        accel = scale.counts_s_to_deg_s(cache.positions.accel_counts_s2) if torque_mode else 0.0
        accel = accel if accel * direction > 0 else 0.0  # only speeding up toward the limit counts
        age = min(max(time.time() - rx.stamp, 0.0), MAX_EXTRAPOLATION_S) if rx.stamp else 0.0
        # where the joint is now, and how fast, not when its TPDO was sampled
        angle = scale.counts_to_deg(rx.position_counts) + velocity * age + 0.5 * accel * age * age
        speed = max(speed_deg_s, abs(velocity + accel * age))
        gain = abs(accel) * LIMIT_ACCEL_MARGIN_S  # speed gained before the brake takes hold
        need = (speed + gain) ** 2 / (2 * decel_deg_s2) + speed * LIMIT_MARGIN_S + 0.5 * gain * LIMIT_ACCEL_MARGIN_S
        if direction > 0 and cfg.max_deg - angle <= need:
            return f"max_deg={cfg.max_deg:g}"
        if direction < 0 and angle - cfg.min_deg <= need:
            return f"min_deg={cfg.min_deg:g}"
        return None

    def brake_if_past(self, frames: LockedCommand, direction: float, speed_deg_s: float, decel_deg_s2: float, what: str,
                      torque_mode: bool = False) -> CommandRejected | None:
        """Inside a command: brake (with its frames) when the command would pass a limit, and
        return the refusal for the caller to raise once the channel is released (then
        :meth:`after_brake`); None when clear."""
        limit = self.limit_ahead(direction, speed_deg_s, decel_deg_s2, torque_mode)
        if limit is None:
            return None
        self._brake(frames)
        return CommandRejected(f"{self.name}: {what} refused: at {self._cache.angle_deg:.2f} deg the joint could not"
                               f" stop before its limit {limit} braking at {decel_deg_s2:g} deg/s^2; it is stopping."
                               " Command away from the limit, or move_to() a target inside it.")

    def after_brake(self, refusal: CommandRejected) -> None:
        """Outside the channel's lock: in a torque mode the brake ends in a quick stop; then the refusal."""
        if self._cache.received.mode in TORQUE_MODES:
            self._channel.stop(Command.QUICK_STOP, "the limit guard's quick stop")
        raise refusal

    def _brake(self, frames: LockedCommand) -> bool:
        """Zero velocity (the drive brakes on its profile deceleration) or zero torque, without
        waiting; only to a drive that is enabled."""
        if self._cache.state != State.OPERATION_ENABLED:
            frames.commanded(False)
            return False
        mode = self._cache.received.mode
        if mode not in VELOCITY_MODES and mode not in TORQUE_MODES:
            frames.commanded(False)
            return False
        if frames.brake(velocity_mode=mode in VELOCITY_MODES):
            self.limit_stops += 1
            return True
        return False

    def guard_limits(self) -> None:
        """Supervisor, every period: brake a velocity- or torque-commanded limited joint whose
        stopping distance has reached its limit (the drive's own 0x607D is the backstop)."""
        if self.config.is_continuous or not self._channel.velocity_commanded:
            return
        cache = self._cache
        velocity = cache.scale.counts_s_to_deg_s(cache.received.velocity_counts_s)
        torque_mode = cache.received.mode in TORQUE_MODES
        decel = self._cache.quick_stop_decel_deg_s2 if torque_mode else self.config.profile_acceleration_deg_s2
        limit = self.limit_ahead(velocity, abs(velocity), decel, torque_mode)
        if limit is None:
            return
        # never waits (the supervisor's period is the host heartbeat's): a command that holds the
        # channel is checked against the limit itself, and the next period brakes if it still must
        frames = self._channel.try_command("the limit guard")
        if frames is None:
            return
        try:
            logger.warning("%s: at %.2f deg moving %.1f deg/s toward its limit %s; braking", self.name,
                           cache.angle_deg, velocity, limit)
            braked = self._brake(frames)
        finally:
            self._channel.release()
        if braked and torque_mode:  # a command holding the channel meanwhile is checked against the limit itself
            self._channel.stop(Command.QUICK_STOP, "the limit guard's quick stop", timeout_s=0.0)

    def stop_velocity(self) -> bool:
        """Watchdog action: zero velocity or zero torque. Never waits: when a command or an
        operation holds the drive (each ends the velocity command itself), it returns False and
        the supervisor tries again at its next period."""
        frames = self._channel.try_command("the watchdog")
        if frames is None:
            return False
        try:
            mode = self._cache.received.mode
            if self._cache.state != State.OPERATION_ENABLED or (mode not in VELOCITY_MODES and mode not in TORQUE_MODES):
                frames.commanded(False)
                return True
            if frames.brake(velocity_mode=mode in VELOCITY_MODES):
                self.watchdog_stops += 1
            return True
        finally:
            self._channel.release()

"""Motion commands, one family per operation mode: profile position (with the set-point
handshake), profile velocity and torque, the cyclic synchronous modes and interpolated position.

Owner: no state of its own. Command threads (the API, ROS callbacks) check a command's input
(finite, in the joint's limits, resolution known) before anything is sent, then decide and send
its frame inside one command of the channel (:meth:`CommandChannel.command`), where the channel
checks that no stop came first. A target the drive takes only by SDO is written inside an
operation of its own (the drive busy, no lock held while the SDO waits), then confirmed in the
channel under that operation: a stop meanwhile wins.

``at_once=True`` (the ROS node's hot thread, which carries every joint's commands): a command that
would wait for its drive first (a mode switch, a target only the SDO takes) raises
:class:`CommandWouldWait` before anything is sent, instead of holding that thread for the round
trips; the caller sends it again where waiting is allowed. Checks of the input and of the drive's
state that need no answer from it are made first (a refusal at once); those that do (the
supported modes, a step judged after a switch) are the waiting call's. A limit guard's quick stop
in a torque mode still takes the channel's lock (a stop: bounded by the other holder's frames).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

from can_config.config import DriveConfig
from can_config.eds import has_object
from can_config.errors import CommandRejected, CommandWouldWait, DriveStateError
from can_config.objects import OD, SUPPORTED_MODE_BIT, OperationMode
from motor_driver.drive.command.busy import Op
from motor_driver.drive.command.channel import CommandChannel, LockedCommand
from motor_driver.drive.command.limits import LimitGuard
from motor_driver.drive.command.power import PowerStateMachine
from motor_driver.drive.command.setpoint import rebase_after_switch
from motor_driver.drive.constants import CONTINUOUS_COMMAND_LIMIT_DEG, ENABLED_CW_MASK
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.verdict import UNREACHABLE, Condition
from motor_driver.protocol.cia402 import FAULT_STATES, SW, State
from motor_driver.protocol.pdo import PdoPlan
from motor_driver.protocol.units import check_counts, check_limits, nearest_equivalent, require_finite

logger = logging.getLogger(__name__)

#: The streamed position modes by number (a dict lookup on every set-point, no enum call),
#: and what each is called and where its target goes
_STREAMING = {int(m): m for m in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION)}
_STREAMED = {OperationMode.CYCLIC_SYNC_POSITION: ("CSP setpoint", OD.TARGET_POSITION),
             OperationMode.INTERPOLATED_POSITION: ("IP setpoint", OD.INTERPOLATION_DATA)}
_ENABLED = State.OPERATION_ENABLED
#: The verdicts a refused set-point names as they are (the cause and what helps)
_SAID_AS_IT_IS = frozenset({Condition.FAULTED, Condition.STOPPED_ITSELF, Condition.HELD, Condition.OUT}) | UNREACHABLE


class Approach(NamedTuple):
    """A command's way toward a limit: its direction, speed, the braking the guard assumes, and what it is."""

    direction: float
    speed_deg_s: float
    decel_deg_s2: float
    what: str


class Motion:
    """Motion commands of one drive, one family per operation mode, limits checked on each."""

    def __init__(self, config: DriveConfig, plan: PdoPlan, cache: DriveCache, channel: CommandChannel, sdo: SdoPort,
                 power: PowerStateMachine, limits: LimitGuard) -> None:
        self.config, self._plan, self._cache, self._channel, self._sdo = config, plan, cache, channel, sdo
        self.name, self.node_id = config.name, config.node_id
        self._power = power
        self._limits = limits
        #: each streamed mode by number: the mode, what its set-point is called, its target object and
        #: whether only an SDO takes that target (no RPDO maps it); judged once from the plan, which is frozen
        self._streams = {int(m): (m, doing, target, plan.rpdo_with(target) is None)
                         for m, (doing, target) in _STREAMED.items()}

    # ------------------------------------------------------------------ checks
    def require_resolution(self, doing: str) -> None:
        """Motion needs the position resolution from the config or the drive, never an assumption."""
        if not self._cache.scale.resolution_known:
            raise CommandRejected(f"{self.name} (node {self.node_id}): {doing} refused: the position resolution is"
                                  " unknown (no counts_per_rev in the config, no 0x608F or 0x60A8 on the drive), so"
                                  " degrees cannot be turned into the drive's units. Set counts_per_rev for this drive"
                                  " (bench: --counts-per-rev N). Nothing was sent.")

    def _require_enabled(self, doing: str, live: bool = True, *, admitted: bool = False) -> None:
        """Read from the drive's verdict: a set-point that moves (``live``) needs it usable; a zero
        (a stop) is taken on late data too, while the state that data last said is Operation
        Enabled (a drive that stopped itself meanwhile must not be sent Enable Operation again:
        on a quick-stop option code 5-7 that is transition 16, back to Operation Enabled). Besides
        the verdict, this driver's own last controlword must be Enable Operation (no stop of ours since).
        ``admitted``: the channel's command that holds its lock has asked :meth:`CommandChannel.admit`."""
        if not admitted:
            self._channel.admit(doing)  # motion held (the lifecycle node inactive) is said before "not enabled"
        verdict = self._power.require_usable(doing, fresh=live)
        word_enabled = self._channel.cw & ENABLED_CW_MASK == ENABLED_CW_MASK
        if verdict.condition is Condition.USABLE and word_enabled:
            return
        snapshot = self._power.snapshot()  # its verdict and the state it was judged from (one read)
        verdict, condition, state = snapshot.verdict, snapshot.verdict.condition, snapshot.state
        late_zero = condition is Condition.LATE and not live and state == _ENABLED
        if (condition is Condition.USABLE or late_zero) and word_enabled:
            return  # usable (judged again since: a newer frame), or a zero on late data of an enabled drive
        if condition is Condition.FAULTED and state in FAULT_STATES:
            raise self._power.fault_error(doing)
        if condition is Condition.LATE and not live and word_enabled:
            raise DriveStateError(f"{verdict.text()} ({doing} refused; nothing was sent: on late data a zero is"
                                  f" taken only while the drive last said OPERATION_ENABLED, and it said {state.name})",
                                  node_id=self.node_id, statusword=self._cache.received.statusword)
        if condition in _SAID_AS_IT_IS:  # faulted since enabled, stopped itself: the verdict says why
            raise DriveStateError(f"{verdict.text()} ({doing} refused; nothing was sent)", node_id=self.node_id,
                                  statusword=self._cache.received.statusword)
        shown = "stopping" if condition in (Condition.USABLE, Condition.LATE) else state.name
        raise DriveStateError(f"{self.name}: {doing} refused: the drive is {shown}; enable() it"
                              " first", node_id=self.node_id, statusword=self._cache.received.statusword)

    def _ensure_mode(self, mode: OperationMode, doing: str, at_once: bool = False, live: bool = True) -> None:
        """Before a motion command, outside the channel: the drive enabled and in ``mode`` (a mode
        switch is an operation of its own; with ``at_once``, :class:`CommandWouldWait` instead)."""
        self._require_free_and_enabled(doing, live)
        if self._cache.received.mode != mode:
            self._would_wait(at_once, doing, f"a switch to {mode.name} first")
            self._power.set_mode(mode)

    def _require_free_and_enabled(self, doing: str, live: bool = True) -> None:
        """No operation of another's runs on the drive (refused at once, not queued), and it is enabled."""
        busy = self._channel.busy
        if busy:
            raise CommandRejected(f"{self.name}: {doing} refused: the drive is busy with {busy};"
                                  " nothing was sent. Send it again when that is done.")
        self._require_enabled(doing, live)

    def _would_wait(self, at_once: bool, doing: str, needs: str) -> None:
        if at_once:
            raise CommandWouldWait(f"{self.name}: {doing} needs {needs}, which waits for the drive; asked to go out"
                                   " at once, nothing was sent")

    def _require_motion(self, mode: OperationMode, doing: str, live: bool = True) -> None:
        """Inside the channel, right before a motion frame, decided with it as one step: the drive
        is usable, this driver's last controlword was Enable Operation (no stop since), the last
        statusword said Operation Enabled, and the mode is still ``mode``. Motion held was asked by
        the channel's command itself, under the same lock (a hold takes it: it cannot come between)."""
        self._require_enabled(doing, live, admitted=True)
        if self._cache.received.mode != mode:
            raise CommandRejected(f"{self.name}: {doing} refused: the drive left {mode.name} meanwhile (now"
                                  f" {self._cache.received.mode}); nothing was sent. Send it again.")

    # ------------------------------------------------------------------ profile position
    def _position_target_counts(self, angle_deg: float) -> int:
        angle = require_finite(f"{self.name} angle", angle_deg, "deg")
        self.require_resolution("a position command")
        cfg = self.config
        scale = self._cache.scale
        if cfg.is_continuous:
            if abs(angle) > CONTINUOUS_COMMAND_LIMIT_DEG:
                raise CommandRejected(f"{self.name}: {angle:g} deg: a continuous joint takes an angle from"
                                      f" -{CONTINUOUS_COMMAND_LIMIT_DEG:g} to {CONTINUOUS_COMMAND_LIMIT_DEG:g} deg"
                                      " and moves the short way to it. Nothing was sent.")
            angle = nearest_equivalent(angle, self._cache.angle_deg)
        else:
            check_limits(self.name, angle, cfg.min_deg, cfg.max_deg)
        return check_counts(self.name, scale.deg_to_counts(angle), "target position")

    def check_position(self, angle_deg: float) -> float:
        """The (multi-turn) angle a position command of ``angle_deg`` would go to, or
        :class:`CommandRejected` naming the limit; nothing is sent."""
        return self._cache.scale.counts_to_deg(self._position_target_counts(angle_deg))

    def move_to(self, angle_deg: float, *, wait: bool = False, timeout_s: float | None = None,
                at_once: bool = False) -> float:
        """Profile-position move to ``angle_deg``; returns the (multi-turn) target in degrees.

        A continuous joint takes the short way round; a limited joint refuses targets beyond
        its limits. Nothing is sent for a refused command.
        """
        counts = self._position_target_counts(angle_deg)
        if at_once and wait:
            raise CommandWouldWait(f"{self.name}: move with wait=True asked to go out at once; nothing was sent")
        self._ensure_mode(OperationMode.PROFILE_POSITION, "move", at_once)
        if self._plan.rpdo_with(OD.CONTROLWORD) is None:
            raise CommandRejected(f"{self.name} (node {self.node_id}): move refused: the controlword cannot be"
                                  " PDO-mapped on this drive, and the set-point handshake's replies come from the"
                                  " receive thread, which never waits for an SDO. Nothing was sent.")
        if self._plan.rpdo_with(OD.TARGET_POSITION) is None:
            # 0x607A only by SDO (the SCHUNK PRL120): written on the caller's thread with the
            # drive busy (no lock held while the SDO waits); the handshake sends only the edge
            self._would_wait(at_once, "move", "its target written by SDO")
            with self._channel.operation("move (target by SDO)") as op:
                self._sdo.write_typed(OD.TARGET_POSITION, 0, counts)
                with self._channel.command("move", op) as frames:
                    self._require_motion(OperationMode.PROFILE_POSITION, "move")
                    frames.setpoint(counts)
        else:
            with self._channel.command("move") as frames:
                self._require_motion(OperationMode.PROFILE_POSITION, "move")
                frames.setpoint(counts)
        if wait:
            self.wait_target_reached(timeout_s)
        return self._cache.scale.counts_to_deg(counts)

    def wait_target_reached(self, timeout_s: float | None = None) -> None:
        cache = self._cache
        if timeout_s is None:
            span = cache.scale.span_deg(self._channel.target_counts - cache.received.position_counts)
            cfg = self.config
            timeout_s = 2.0 + span / cfg.profile_velocity_deg_s + 2 * cfg.profile_velocity_deg_s / cfg.profile_acceleration_deg_s2

        since = Op(0, "move", self._channel.generation)  # a stop of ours after this ends the wait as ours

        def reached() -> bool:
            if cache.state in FAULT_STATES:
                raise self._power.fault_error("move")
            self._channel.check(since, "move")
            if (stopped := self._power.stopped_itself("the move")) is not None:
                raise stopped
            return self._channel.handshake_idle and bool(cache.received.statusword & SW.TARGET_REACHED)

        behind = self._power.read_behind()
        if not cache.wait_until(reached, timeout_s, behind=behind):
            where = (f" within {timeout_s:.1f} s (at {cache.angle_deg:.2f} deg, target"
                     f" {cache.scale.counts_to_deg(self._channel.target_counts):.2f} deg)")
            raise self._power.timed_out(behind, (f"{self.name}: target not read as reached{where}", ""),
                                        (f"{self.name}: target not reached{where}", ""))
        # the statusword comes on change, the position on SYNC: wait for a position sampled
        # after the drive said 'reached', so the caller's snapshot is not one period old
        seq = cache.position_seq
        cache.wait_until(lambda: cache.position_seq != seq, 3 * cache.sync_period_s + 0.05)

    def check_profile_velocity(self, velocity_deg_s: float) -> int:
        """``velocity_deg_s`` as a profile velocity in drive units, or :class:`CommandRejected`
        naming the range; nothing is sent."""
        speed = require_finite(f"{self.name} profile velocity", velocity_deg_s, "deg/s")
        self.require_resolution("a profile velocity")
        if not 0 < speed <= self.config.max_velocity_deg_s:
            raise CommandRejected(f"{self.name}: profile velocity {speed:g} deg/s: allowed 0 < speed <="
                                  f" {self.config.max_velocity_deg_s:g} (max_velocity_deg_s). Nothing was sent.")
        units = self._cache.scale.magnitude_to_drive(speed)
        if units == 0:  # 0x6081 = 0: the drive would never move, and the move's time bound never end
            raise CommandRejected(f"{self.name}: profile velocity {speed:g} deg/s is below the drive's velocity"
                                  f" resolution (one unit of 0x6081 is {abs(self._cache.scale.counts_s_to_deg_s(1.0)):g}"
                                  " deg/s); give a faster one. Nothing was sent.")
        return units

    def set_profile_velocity(self, velocity_deg_s: float) -> None:
        """The speed of the following profile-position moves (0x6081), at most max_velocity_deg_s."""
        units = self.check_profile_velocity(velocity_deg_s)
        with self._channel.operation("profile velocity"):  # an SDO round trip: busy, not the lock
            self._sdo.write_typed(OD.PROFILE_VELOCITY, 0, units)

    def restore_profile_velocity(self) -> None:
        """The configured profile velocity again (``profile_velocity_deg_s``, as boot writes it),
        where the drive has 0x6081: a move that asks for no speed of its own never runs at the
        speed an earlier one set."""
        if has_object(self._sdo.od, OD.PROFILE_VELOCITY):
            self.set_profile_velocity(self.config.profile_velocity_deg_s)

    # ------------------------------------------------------------------ velocity and torque
    def _checked_velocity(self, velocity_deg_s: float) -> tuple[float, int]:
        velocity = require_finite(f"{self.name} velocity", velocity_deg_s, "deg/s")
        self.require_resolution("a velocity command")
        vmax = self.config.max_velocity_deg_s
        if abs(velocity) > vmax:
            raise CommandRejected(f"{self.name}: velocity {velocity:g} deg/s is beyond the limit"
                                  f" max_velocity_deg_s={vmax:g} (allowed -{vmax:g} to {vmax:g}). Nothing"
                                  " was sent.")
        return velocity, check_counts(self.name, self._cache.scale.deg_s_to_counts_s(velocity), "velocity")

    def _checked_torque(self, torque_nm: float) -> float:
        torque = require_finite(f"{self.name} torque", torque_nm, "Nm")
        self.require_resolution("a torque command")  # its limit guard works in degrees
        scale = self._cache.scale
        limit = self.config.max_torque_nm or scale.rated_torque_nm * scale.gear_ratio
        if abs(torque) > limit:
            raise CommandRejected(f"{self.name}: torque {torque:g} Nm is beyond the limit max_torque_nm={limit:g}"
                                  f" (allowed -{limit:g} to {limit:g} Nm). Nothing was sent.")
        return torque

    def _target(self, mode: OperationMode, doing: str, value: int, *, live: bool, guard: Approach,
                check_step: float | None = None, at_once: bool = False) -> None:
        """A velocity or torque target in ``mode``: limit-guarded and sent in one command of the
        channel; on a drive that takes it only by SDO, written inside an operation first."""
        torque_mode = mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE)
        index = OD.TARGET_TORQUE if torque_mode else OD.TARGET_VELOCITY
        if self._plan.rpdo_with(index) is None:
            self._would_wait(at_once, doing, "its target written by SDO")
            with self._channel.operation(f"{doing} (target by SDO)") as op:
                self._sdo.write_typed(index, 0, value)
                self._send_target(mode, doing, value, live, guard, check_step, op)
            return
        self._send_target(mode, doing, value, live, guard, check_step, None)

    def _send_target(self, mode: OperationMode, doing: str, value: int, live: bool, guard: Approach,
                     check_step: float | None, op: Op | None) -> None:
        torque_mode = mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE)
        with self._channel.command(doing, op) as frames:
            refusal = self._limits.brake_if_past(frames, guard.direction, guard.speed_deg_s, guard.decel_deg_s2,
                                                 guard.what, torque_mode)
            if refusal is None:
                self._require_motion(mode, doing, live)
                if check_step is not None:
                    self._check_stream_step(check_step)
                self._emit(frames, torque_mode, value, live, by_sdo=op is not None, stream=check_step is not None)
        if refusal is not None:
            self._limits.after_brake(refusal)

    @staticmethod
    def _emit(frames: LockedCommand, torque_mode: bool, value: int, live: bool, *, by_sdo: bool, stream: bool) -> None:
        if by_sdo:
            frames.commanded(live)
        elif torque_mode:
            frames.torque(value, live=live)
        else:
            frames.velocity(value, live=live, stream=stream)

    def _check_stream_step(self, velocity: float) -> None:
        scale = self._cache.scale
        previous = scale.counts_s_to_deg_s(self._channel.stream_velocity_counts_s) \
            if self._channel.velocity_commanded else 0.0
        max_step = self._cache.quick_stop_decel_deg_s2 * 2 * self._cache.sync_period_s
        if abs(velocity) > abs(previous) and abs(velocity - previous) > max_step:
            raise CommandRejected(f"{self.name}: CSV set-point {velocity:g} deg/s jumps"
                                  f" {abs(velocity - previous):.1f} deg/s from the last one ({previous:g});"
                                  f" at most {max_step:.1f} deg/s per step speeding up (the quick-stop"
                                  " deceleration over two SYNC periods). Ramp it. Nothing was sent.")

    def set_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        """Profile-velocity command in deg/s, limited by max_velocity_deg_s; feeds the watchdog."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.PROFILE_VELOCITY, "velocity command", at_once, live=velocity != 0.0)
        self._target(OperationMode.PROFILE_VELOCITY, "velocity command", counts_s, live=velocity != 0.0,
                     guard=Approach(velocity, abs(velocity), self.config.profile_acceleration_deg_s2,
                                    f"velocity {velocity:g} deg/s"), at_once=at_once)

    def stream_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        """Cyclic synchronous velocity (CSV): one target per SYNC period, which the drive takes
        at the next SYNC without a ramp of its own (the caller's stream is the ramp). Limited by
        max_velocity_deg_s; speeding up by more than the quick-stop deceleration over two SYNC
        periods in one step is refused (slowing down never is); feeds the watchdog. Refused on a
        drive whose 0x6502 does not list CSV."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point", at_once, live=velocity != 0.0)
        self._target(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point", counts_s, live=velocity != 0.0,
                     guard=Approach(velocity, abs(velocity), self._cache.quick_stop_decel_deg_s2,
                                    f"CSV velocity {velocity:g} deg/s"), check_step=velocity, at_once=at_once)

    def _torque_command(self, torque_nm: float, mode: OperationMode, doing: str, what: str, at_once: bool) -> None:
        torque = self._checked_torque(torque_nm)
        self._ensure_mode(mode, doing, at_once, live=torque != 0.0)
        self._target(mode, doing, self._cache.scale.nm_to_permille(torque), live=torque != 0.0,
                     guard=Approach(torque, 0.0, self._cache.quick_stop_decel_deg_s2, f"{what} {torque:g} Nm"),
                     at_once=at_once)

    def set_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        """Profile-torque command in Nm at the joint, limited by max_torque_nm; feeds the watchdog."""
        self._torque_command(torque_nm, OperationMode.PROFILE_TORQUE, "torque command", "torque", at_once)

    def stream_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        """Cyclic synchronous torque (CST): one torque target in Nm at the joint per SYNC period,
        limited by max_torque_nm; feeds the watchdog (which sends zero torque). Refused on a
        drive whose 0x6502 does not list CST."""
        self._torque_command(torque_nm, OperationMode.CYCLIC_SYNC_TORQUE, "CST set-point", "CST torque", at_once)

    @staticmethod
    def _as_configured(mode: str, streamed: Callable[..., object], profiled: Callable[..., object],
                       value: float, at_once: bool) -> None:
        """A command in the drive's configured way: one set-point of a stream (``mode`` is
        ``cyclic``), else through the profile."""
        if mode == "cyclic":
            streamed(value, at_once=at_once)
        else:
            profiled(value, at_once=at_once)

    def command_position(self, angle_deg: float, *, at_once: bool = False) -> None:
        """A position command in the drive's configured way: a profile-position move, or one
        set-point of a stream (``position_mode: cyclic``: CSP or IP, no handshake)."""
        self._as_configured(self.config.position_mode, self.stream_position, self.move_to, angle_deg, at_once)

    def command_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        """A velocity command in the drive's configured way: profile velocity, or CSV
        (``velocity_mode: cyclic``)."""
        self._as_configured(self.config.velocity_mode, self.stream_velocity, self.set_velocity, velocity_deg_s,
                            at_once)

    def command_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        """A torque command in the drive's configured way: profile torque, or CST
        (``torque_mode: cyclic``)."""
        self._as_configured(self.config.torque_mode, self.stream_torque, self.set_torque, torque_nm, at_once)

    # ------------------------------------------------------------------ streamed positions
    def streaming(self) -> bool:
        """The drive is in a streamed position mode (CSP or IP): a set-point goes out without a switch."""
        return self._cache.received.mode in _STREAMING

    def start_stream(self) -> None:
        """Into the streamed position mode (CSP, else IP) without a set-point, where it is not yet:
        the drive holds where its shaft is, and the next set-point is judged from a position sampled
        after the switch (a trajectory group's first SYNC then carries its first set-point alone)."""
        if self.streaming():
            return
        mode = self._mode_to_stream_in()
        self._ensure_mode(mode, _STREAMED[mode][0])
        rebase_after_switch(self._cache, self._channel.forget)

    def stream_position(self, angle_deg: float, *, max_step_deg: float | None = None, at_once: bool = False) -> None:
        """One position set-point per SYNC period, no handshake: cyclic synchronous position,
        or interpolated position (0x60C1:1, controlword bit 4 "enable ip mode") on a drive
        whose 0x6502 lists IP but not CSP (the SCHUNK PRL120 is one).

        Refuses a setpoint that jumps further than ``max_step_deg`` (default: max velocity
        over two SYNC periods) from the previous one: a streamed trajectory must be smooth.
        """
        counts = self._position_target_counts(angle_deg)
        stream = self._streams.get(self._cache.received.mode)  # one read decides: streaming already, or not
        if stream is None and at_once:  # a switch first (the supported modes may take an SDO too)
            self._require_free_and_enabled("a streamed set-point")
            self._would_wait(True, "a streamed set-point", "a switch to a streamed position mode first")
        switching = stream is None
        mode, doing, target, by_sdo = stream or self._streams[self._mode_to_stream_in()]
        if by_sdo or switching:  # before an SDO or a mode switch; streaming by RPDO
            self._ensure_mode(mode, doing, at_once)  # already, the channel decides busy, enabled and mode with the frame
            if by_sdo:
                self._would_wait(at_once, doing, "its target written by SDO")
            if switching:  # the first set-point: from where the drive holds after the switch (setpoint.py)
                rebase_after_switch(self._cache, self._channel.forget)
                counts = self._position_target_counts(angle_deg)
        if by_sdo:
            with self._channel.operation(f"{doing} (target by SDO)") as op:
                self._check_position_step(counts, max_step_deg)
                self._sdo.write_typed(target, 1 if target == OD.INTERPOLATION_DATA else 0, counts)
                with self._channel.command(doing, op) as frames:
                    self._require_motion(mode, doing)
                    frames.stream_position(mode, counts, sdo_written=True)
            return
        with self._channel.command(doing) as frames:
            self._require_motion(mode, doing)
            self._check_position_step(counts, max_step_deg)
            frames.stream_position(mode, counts, sdo_written=False)

    def _check_position_step(self, counts: int, max_step_deg: float | None) -> None:
        if max_step_deg is None:
            max_step_deg = self.config.max_velocity_deg_s * 2 * self._cache.sync_period_s
        step = self._cache.scale.span_deg(counts - self._channel.target_counts)
        if step > max_step_deg:
            raise CommandRejected(f"{self.name}: CSP setpoint jumps {step:.3f} deg from the last one; at most"
                                  f" {max_step_deg:.3f} deg per step (max_velocity_deg_s over two SYNC"
                                  " periods) is allowed. Nothing was sent. A point-to-point move is a profile-position"
                                  " move (move_to, the move_joint action).")

    def _mode_to_stream_in(self) -> OperationMode:
        """The streamed position mode to switch into: CSP where 0x6502 lists it, else IP."""
        supported = self._power.supported_modes()
        for candidate in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            if supported >> SUPPORTED_MODE_BIT[candidate] & 1:
                return candidate
        raise CommandRejected(f"{self.name}: streaming set-points needs cyclic synchronous or interpolated"
                              f" position; node {self.node_id} supports neither (0x6502 = 0x{supported:08X}).")

"""The simulated drive's set-point generator per mode, its servo loops and the motor and load
plant, software position limits and following error. Runner thread only.
"""

from __future__ import annotations

import logging
import math

import can

from can_config.objects import OD, OperationMode
from virtual_can.sim.drive.model import (
    CW_HALT,
    CYCLIC_GAP_S,
    EMCY_FOLLOWING_ERROR,
    EMCY_POSITION_LIMIT,
    LATCH_AHEAD_MAX_S,
    LIMIT_TOLERANCE_REV,
    PHYSICS_STEP_S,
    POWERED,
    QUICK_STOP_HOLDS,
    State,
)
from virtual_can.sim.drive.statemachine import StateMachine

logger = logging.getLogger(__name__)


class Plant(StateMachine):
    """Layer 3: set-points, servo and plant."""

    def _move(self, now: float, dt: float) -> list[can.Message]:
        store = self.store
        k = self._rad_per_count
        halt = bool(int(store.get(OD.CONTROLWORD, 0)) & CW_HALT)  # type: ignore[arg-type]
        mode = self.mode
        rated = float(store.get(OD.RATED_TORQUE, 0, 0)) / 1000.0 if store.has(OD.RATED_TORQUE) else 0.0  # type: ignore[arg-type]
        rated = rated or self.params.rated_torque_nm
        out: list[can.Message] = []
        if self.state in POWERED:
            self._setpoint_step(mode, halt, now, dt)
            # controller + plant, in motor radians, in sub-steps of at most PHYSICS_STEP_S so the
            # servo loops stay stable however late the simulator thread gets to run
            torque_mode = mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE) \
                and self.state == State.OPERATION_ENABLED
            position_loop = mode not in (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY) \
                or self.state != State.OPERATION_ENABLED or halt
            limit = float(store.get(OD.MAX_TORQUE, 0, 3000)) / 1000.0 * rated  # type: ignore[arg-type]
            self._servo(dt, k, limit, self._target_torque(rated) if torque_mode else None, position_loop)
            if not position_loop:  # velocity modes: no position loop, the set-point follows the shaft
                self.sp_pos = self.position_counts
            out += self._check_following(now, mode)
        else:
            self.omega = 0.0  # holding brake
            self.torque_nm = 0.0
            self._vel_integral = 0.0
            self.sp_pos = self.position_counts
            self.sp_vel = self.sp_acc = 0.0
        self._publish_actuals(rated)
        return out

    def _publish_actuals(self, rated: float) -> None:
        """Position, velocity, torque and following error into the object dictionary, in the drive's units."""
        store, k = self.store, self._rad_per_count
        self._publish_position()
        store.values[(OD.VELOCITY_ACTUAL, 0)] = self._as_type(OD.VELOCITY_ACTUAL, self.omega / k / self._vconv)
        if store.has(OD.TORQUE_ACTUAL):
            store.values[(OD.TORQUE_ACTUAL, 0)] = self._as_type(OD.TORQUE_ACTUAL,
                                                                self.torque_nm / rated * 1000.0)
        if store.has(OD.FOLLOWING_ERROR_ACTUAL):
            store.values[(OD.FOLLOWING_ERROR_ACTUAL, 0)] = self._as_type(
                OD.FOLLOWING_ERROR_ACTUAL, self.sp_pos - self.position_counts)

    def _latch_position(self, at: float) -> None:
        """The position actual (0x6064) at ``at`` (the runner's clock: a SYNC's moment), as a CiA 402
        drive latches it at the SYNC: the plant's state of the last tick moved on at the shaft's speed
        to that moment (never back, at most LATCH_AHEAD_MAX_S), not the last tick's, up to a tick old.
        The next tick writes its own again."""
        ahead = min(max(0.0, at - self._plant_at), LATCH_AHEAD_MAX_S)
        if ahead and self.omega:
            counts = (self.theta + self.omega * ahead) / self._rad_per_count + self.position_offset
            self.store.values[(OD.POSITION_ACTUAL, 0)] = self._as_type(OD.POSITION_ACTUAL, counts)

    def _setpoint_step(self, mode: int, halt: bool, now: float, dt: float) -> None:
        """The set-point generator of a powered drive, one tick: the mode's own, a halt, or the
        quick-stop / fault-reaction ramp."""
        decel = self._v(OD.PROFILE_DECELERATION, 0, 16384) or 16384.0
        accel = self._v(OD.PROFILE_ACCELERATION, 0, 16384) or 16384.0
        vmax = self._v(OD.PROFILE_VELOCITY, 0, 4096) or 4096.0
        vlimit = self._v(OD.MAX_PROFILE_VELOCITY, 0, 0) or vmax
        vmax = min(vmax, vlimit)
        if self.state != State.OPERATION_ENABLED:
            # 0x605A: 1 and 5 brake on the slow-down ramp (0x6084), the others on the quick-stop ramp
            # (0x6085; 3, 4, 7 and 8, the current and voltage limits, modelled so); 5-8 then stay in
            # Quick Stop Active
            option = self.quick_stop_option if self.state == State.QUICK_STOP_ACTIVE else 2
            rate = decel if option in (1, 5) else self._v(OD.QUICK_STOP_DECELERATION, 0, 65536) or 65536.0
            self._ramp_velocity(0.0, rate, rate, dt)
            if abs(self.sp_vel) < 1e-6 and option not in QUICK_STOP_HOLDS:
                self.state = State.FAULT if self.state == State.FAULT_REACTION_ACTIVE else State.SWITCH_ON_DISABLED
        elif halt and mode in (OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY, OperationMode.HOMING):
            self._ramp_velocity(0.0, decel, decel, dt)
        elif mode == OperationMode.PROFILE_POSITION and self.pp_target is not None:
            self._track_position(self.pp_target, vmax, accel, decel, dt)
        elif mode == OperationMode.PROFILE_VELOCITY:
            target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
            self._ramp_velocity(max(-vlimit, min(vlimit, target_v)), accel, decel, dt)
        elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION) \
                and self.pp_target is not None:
            self._cyclic_position_step(self.pp_target, now)
        elif mode == OperationMode.CYCLIC_SYNC_VELOCITY:
            target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
            if self.store.has(OD.VELOCITY_OFFSET):
                target_v += self._v(OD.VELOCITY_OFFSET, 0, 0)
            self.sp_vel, self.sp_acc = max(-vlimit, min(vlimit, target_v)), 0.0
        elif mode == OperationMode.HOMING and self.homing_active:
            self._homing_step(accel, decel, dt)
        elif mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE):
            # no set-point of its own: it follows the shaft, so a stop (quick stop, halt, a
            # mode change) starts from where the joint is and how fast it turns
            self.sp_pos, self.sp_vel, self.sp_acc = self.position_counts, self.omega / self._rad_per_count, 0.0
        else:
            self.sp_vel = self.sp_acc = 0.0

    def _cyclic_position_step(self, target: float, now: float) -> None:
        """CSP / IP: a new cyclic set-point is reached over one SYNC cycle, or over the cycles
        since the one left behind was written, when this process took several SYNCs' set-points
        in one go (it ran late): the set-point then moves at the stream's speed, not several
        cycles' way in one (a velocity many times the stream's, fed forward over a late tick).
        Linear interpolation, as drives do (0x60C2): no jump per cycle, no velocity left over."""
        last = self._csp_last
        done = min(1.0, (now - self._csp_t) / self._csp_period)
        if target != last:
            fresh = last is not None and now - self._csp_t <= CYCLIC_GAP_S
            # from where the set-point is now on its way to the one left behind; from where it
            # stands if something else moved it since this step's last (a quick stop's ramp)
            on_path = fresh and last is not None and self.sp_pos == self._csp_left
            here = self._csp_from + (last - self._csp_from) * done if on_path and last is not None else self.sp_pos
            self._csp_from = here if fresh else target
            cycles = max(1, self._csp_written - self._csp_sync) if fresh else 1
            self._csp_period = self._sync_period_s * cycles
            self._csp_last, self._csp_t, self._csp_sync = target, now, self._csp_written
            done = 0.0
        if done >= 1.0:
            self.sp_pos, self.sp_vel = target, 0.0
        else:
            self.sp_vel = (target - self._csp_from) / self._csp_period
            self.sp_pos = self._csp_from + (target - self._csp_from) * done
        self.sp_acc = 0.0
        self._csp_left = self.sp_pos

    def _homing_step(self, accel: float, decel: float, dt: float) -> None:
        """Homing: toward the index at the homing speed; 20 revolutions without it is an error."""
        speed = self._v(OD.HOMING_SPEEDS, 1, 1000) or 1000.0
        raw_index = self.params.index_position_counts
        raw_now = self.sp_pos - self.position_offset
        direction = 1.0 if raw_index > raw_now else -1.0
        self._ramp_velocity(direction * speed, accel, decel, dt)
        if (raw_index - (self.sp_pos - self.position_offset)) * direction <= 0:
            self.theta = raw_index * self._rad_per_count
            self._home_here()
        elif abs(self.sp_pos - self._homing_start) > 20 * self.units_per_motor_rev:
            self.homing_active = False
            self.homing_error = True

    def _target_torque(self, rated: float) -> float:
        """PT / CST: 0x6071 (+ the torque offset 0x60B2 where the drive has it), in Nm."""
        permille = float(self.store.get(OD.TARGET_TORQUE, 0, 0))  # type: ignore[arg-type]
        if self.mode == OperationMode.CYCLIC_SYNC_TORQUE and self.store.has(OD.TORQUE_OFFSET):
            permille += float(self.store.get(OD.TORQUE_OFFSET, 0, 0))  # type: ignore[arg-type]
        return permille / 1000.0 * rated

    def _servo(self, dt: float, k: float, limit: float, target_tau: float | None, position_loop: bool) -> None:
        """Position loop (P) -> velocity loop (PI) -> current loop (first-order lag) -> motor
        and load (inertia, viscous and Coulomb friction, external load), in motor radians."""
        p = self.params
        kp, kv, ki = self._gains
        inertia = p.inertia_kg_m2
        steps = max(1, math.ceil(dt / PHYSICS_STEP_S))
        h = dt / steps
        alpha = h / (p.torque_lag_s + h)  # the current loop's lag, backward Euler (stable for any h)
        # the profile's set-point moves on within the tick with its acceleration (the set-point
        # velocity ramps, the feed-forward with it): a tick that comes late, 10-20 ms on a busy
        # machine, gives the same torque as ten on time, not a velocity step and then friction
        acc = self.sp_acc * k
        v_end = self.sp_vel * k
        v0 = v_end - acc * dt
        sp_rad = self.sp_pos * k - 0.5 * (v0 + v_end) * dt  # the profile's position at the start of the tick
        i_max = limit / ki if ki > 0 else 0.0
        stalled = self.faults.stalled
        omega, theta, tau, integral = self.omega, self.theta, self.torque_nm, self._vel_integral
        offset_rad = self.position_offset * k
        for i in range(steps):
            if target_tau is not None:
                tau_cmd = target_tau
            else:  # the set-point moves on within the tick as the shaft does: both at the sub-step's start
                t = h * i
                v_cmd = p.velocity_ff * (v0 + acc * t) + (
                    kp * (sp_rad + v0 * t + 0.5 * acc * t * t - theta - offset_rad) if position_loop else 0.0)
                err = v_cmd - omega
                integral = max(-i_max, min(i_max, integral + err * h))  # anti-windup
                tau_cmd = kv * err + ki * integral
            tau_cmd = max(-limit, min(limit, tau_cmd))
            tau += alpha * (tau_cmd - tau)
            if stalled:
                omega = 0.0
                continue
            drive = tau - p.load_nm - p.viscous_nm_s_rad * omega
            if omega == 0.0 and abs(drive) <= p.coulomb_nm:
                continue  # static friction holds the shaft
            friction = math.copysign(p.coulomb_nm, omega if omega != 0.0 else drive)
            new_omega = omega + h * (drive - friction) / inertia
            if omega != 0.0 and new_omega * omega < 0.0 and abs(drive) <= p.coulomb_nm:
                new_omega = 0.0  # friction stops the shaft; it does not reverse it
            theta += h * 0.5 * (omega + new_omega)
            omega = new_omega
        self.omega, self.theta, self.torque_nm, self._vel_integral = omega, theta, tau, integral

    def _limits_on(self) -> bool:
        """0x607D holds software position limits (CiA 402: low >= high switches them off)."""
        store = self.store
        return store.has(OD.SOFTWARE_POSITION_LIMIT, 2) and \
            float(store.get(OD.SOFTWARE_POSITION_LIMIT, 1)) < float(store.get(OD.SOFTWARE_POSITION_LIMIT, 2))  # type: ignore[arg-type]

    def _check_position_limits(self, now: float) -> list[can.Message]:
        """0x607D while enabled: moving on beyond a software position limit is a fault."""
        if self.state != State.OPERATION_ENABLED or not self._limits_on():
            return []
        low = float(self.store.get(OD.SOFTWARE_POSITION_LIMIT, 1))  # type: ignore[arg-type]
        high = float(self.store.get(OD.SOFTWARE_POSITION_LIMIT, 2))  # type: ignore[arg-type]
        pos = self.position_counts
        tolerance = LIMIT_TOLERANCE_REV * self.units_per_motor_rev
        if (pos > high + tolerance and self.omega > 0) or (pos < low - tolerance and self.omega < 0):
            logger.warning("node %d: position %.0f beyond the software limit [%.0f, %.0f]", self.node_id, pos, low, high)
            return self._raise_fault(EMCY_POSITION_LIMIT, now)
        return []

    def _check_following(self, now: float, mode: int) -> list[can.Message]:
        if mode not in (OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_POSITION,
                        OperationMode.INTERPOLATED_POSITION) or self.state != State.OPERATION_ENABLED:
            self.following_since = None
            return []
        window = int(self.store.get(OD.FOLLOWING_ERROR_WINDOW, 0, 0))  # type: ignore[arg-type]
        if window <= 0 or window == 0xFFFFFFFF:
            return []
        if abs(self.sp_pos - self.position_counts) <= window:
            self.following_since = None
            return []
        if self.following_since is None:
            self.following_since = now
        timeout = int(self.store.get(OD.FOLLOWING_ERROR_TIMEOUT, 0, 0)) / 1000.0  # type: ignore[arg-type]
        if now - self.following_since >= timeout:
            self.following_since = None
            return self._raise_fault(EMCY_FOLLOWING_ERROR, now)
        return []

    def _ramp_velocity(self, target: float, accel: float, decel: float, dt: float) -> None:
        dv = target - self.sp_vel
        rate = accel if abs(target) > abs(self.sp_vel) and target * self.sp_vel >= 0 else decel
        step = rate * dt
        self.sp_acc = math.copysign(rate, dv) if abs(dv) > step else dv / dt if dt else 0.0
        v_start = self.sp_vel
        self.sp_vel = target if abs(dv) <= step else self.sp_vel + math.copysign(step, dv)
        self.sp_pos += 0.5 * (v_start + self.sp_vel) * dt  # exact for the constant acceleration

    def _track_position(self, target: float, vmax: float, accel: float, decel: float, dt: float) -> None:
        """Online trapezoidal profile toward ``target`` (counts)."""
        dist = target - self.sp_pos
        v = self.sp_vel
        if abs(dist) < 0.5 and abs(v) < decel * dt:
            self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, 0.0
            return
        direction = math.copysign(1.0, dist)
        stop_dist = v * v / (2 * decel)
        if v * direction > 0 and stop_dist >= abs(dist):
            # braking: the constant deceleration that stops exactly on the target (a step late,
            # it is a little more than the profile's), so the set-point ends without a jump
            need = v * v / (2 * abs(dist))
            if abs(v) <= need * dt:
                self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, -v / dt
                return
            self.sp_acc = -direction * need
            self.sp_pos += v * dt + 0.5 * self.sp_acc * dt * dt
            self.sp_vel = v + self.sp_acc * dt
            return
        desired = direction * vmax
        # never ask for more speed than allows stopping on target
        cap = math.sqrt(2 * decel * abs(dist))
        desired = max(-cap, min(cap, desired))
        self._ramp_velocity(desired, accel, decel, dt)
        if (target - self.sp_pos) * direction < 0:  # passed it within this step
            self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, 0.0

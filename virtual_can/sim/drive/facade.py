"""The :class:`SimulatedDrive` the runner uses: the layers stacked, plus the tick that
advances them.

A simulated CiA 402 servo drive, written from CiA 301 / CiA 402 on its own.

One :class:`SimulatedDrive` is one CANopen node: NMT, SDO server, heartbeat producer, EMCY
producer with error register and history, PDOs configured from its object dictionary (and
re-configurable by SDO, with the CiA 301 procedure enforced), the CiA 402 state machine with
quick stop and fault reaction, the modes PP, PV, PT, CSP, IP and homing, the CiA 301 heartbeat
consumer (0x1016, armed by the first heartbeat it watches, EMCY 0x8130 on expiry) with the CiA
402 abort connection option (0x6007: 0 nothing, 1 fault, 2 disable voltage, 3 quick stop; a
fault on a drive without 0x6007, as its vendor would most likely have it), the
software position limits (0x607D: moving beyond one while enabled is a fault, EMCY 0x8612), and
a motion model
(inertia, viscous friction, load torque, torque limit) behind a position/velocity controller.
Position, velocity and torque are reported in the drive's units: encoder counts, counts/s
and per mille of the rated torque.

It does no I/O: :meth:`on_frame` and :meth:`tick` return the frames to send; a
:class:`~virtual_can.sim.runner.DriveSimulator` moves them on a python-can bus.

Owner: the simulator's runner thread, all of it.
"""

from __future__ import annotations

import logging
import math

import can

from can_config.objects import OD, FunctionCode, NmtState
from virtual_can.sim.drive.comm import CommNode
from virtual_can.sim.drive.model import EMCY_STO, POWERED, State

logger = logging.getLogger(__name__)


#: A tick longer than this (a late simulator thread) moves the plant in parts this long while its
#: software position limits are on, each part's end checked against them (the runner's own tick)
LIMIT_CHECK_S = 0.002


class SimulatedDrive(CommNode):
    """One simulated CiA 402 node. Not thread-safe: driven by one runner thread."""

    def power_cycle(self, now: float, off_s: float) -> None:
        """Fault injection: power off for ``off_s``, then boot again (boot-up message)."""
        self.faults.power_off_until = now + off_s
        self.state = State.NOT_READY_TO_SWITCH_ON

    def tick(self, now: float, dt: float, bus_now: float | None = None) -> list[can.Message]:
        """Advance the simulation by ``dt`` seconds; return the frames the drive sends now (behind
        any held: :meth:`release`). ``bus_now``: the bus time up to which every frame was handled,
        that the watch on other nodes is judged on (default ``now``: the caller keeps one clock)."""
        return self._in_order(self._advance(now, dt, bus_now))

    def _advance(self, now: float, dt: float, bus_now: float | None) -> list[can.Message]:
        bus_now = now if bus_now is None else bus_now
        self._now = now
        if self.faults.power_off_until:
            if now < self.faults.power_off_until:
                return []
            self.faults.power_off_until = 0.0
            return self._reset_node(now)
        out: list[can.Message] = []
        while self.faults.pending:
            out += self._raise_fault(self.faults.pending.pop(0), now)
        if self._pending_emcy_reset:
            self._pending_emcy_reset = False
            out.append(self._emcy(0x0000, 0))
        delayed = self._delayed_sdo
        if delayed is not None and now >= delayed[0]:
            self._delayed_sdo = None
            out += self._sdo(delayed[1])
        if self.faults.sto_low and self.state in POWERED and self.state != State.FAULT_REACTION_ACTIVE:
            out += self._raise_fault(EMCY_STO, now)
        if self._consumer_seen:
            out += self._check_consumers(now, bus_now)
        if self._guarded_at is not None:
            out += self._check_life_guard(now, bus_now)
        if self._cycle_rpdos:  # the objects hold the last value written; the drive reads them once
            written: set[int] = set()
            for pdo, data in self._cycle_rpdos:
                written |= self._write_rpdo(pdo, data)
            self._cycle_rpdos.clear()
            self._act_on(written)
        if self._slow_transition is not None and now >= self._slow_transition[1]:
            new, _ = self._slow_transition
            self._slow_transition = None
            self._enter(new)
        out += self._move_within_limits(now, dt)
        self._update_status()
        if self.faults.unplugged:
            return []
        if self.nmt == NmtState.OPERATIONAL:
            out += self._event_tpdos(now)
        period_ms = int(self.store.get(OD.PRODUCER_HEARTBEAT_TIME, 0, 0))  # type: ignore[arg-type]
        if period_ms and now >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + period_ms / 1000.0, now)
            out.append(self._msg(FunctionCode.HEARTBEAT + self.node_id, bytes([self.nmt])))
        return out

    def _move_within_limits(self, now: float, dt: float) -> list[can.Message]:
        """The plant moved by ``dt`` up to ``now``, its software position limits checked every
        LIMIT_CHECK_S of it while they are on: a late tick (a busy machine's simulator thread)
        faults at the crossing as a tick on time does, and its quick stop starts there, not a late
        tick's travel beyond it (the overshoot a drive's limit allows is the machine's, not the CPU's)."""
        chunks = 1
        if dt > LIMIT_CHECK_S and self.state == State.OPERATION_ENABLED and self._limits_on():
            chunks = math.ceil(dt / LIMIT_CHECK_S)
        out: list[can.Message] = []
        for i in range(1, chunks + 1):
            at = now - dt * (chunks - i) / chunks
            out += self._move(at, dt / chunks)
            self._plant_at = at
            out += self._check_position_limits(at)
        return out

    def shaft(self) -> tuple[float, float, float]:
        """(angle rad, speed rad/s, the runner's time they are of): the motor shaft's motion as the
        physics last moved it (a test's truth to judge what the driver measured by)."""
        return self.theta, self.omega, self._plant_at

    def status_line(self) -> str:
        return (f"node {self.node_id:3d} {self.name:<10} NMT={self.nmt.name:<15} {self.state.name:<22}"
                f" mode={self.mode:<2} pos={self.position_counts:12.0f} vel={self.omega / self._rad_per_count:9.0f}"
                f" torque={self.torque_nm:+.3f}Nm err=0x{self.error_code:04X}")

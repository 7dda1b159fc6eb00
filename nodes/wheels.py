"""What the drive system says of a wheel, and which wheels it has left out (pure: no rclpy).

:func:`wheel_problem` names the real cause a wheel cannot be driven (another master, lost,
stale data, a fault, not armed) and the action that helps; every refusal and diagnostic of the
drive system uses it. :func:`odometry_sample` turns a wheel's snapshot into what the odometry may
use (:mod:`motor_driver.rover.odometry`). :class:`WheelsOut` is ``on_wheel_loss: continue``'s book of
the wheels left out, and when each may come back.

Owner: the drive system's control loop (one thread, the executor that runs its tick).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from motor_driver.drive import DriveState
from motor_driver.protocol.cia402 import FAULT_STATES, State
from motor_driver.rover.odometry import WheelSample

ARM = "arm the rover with the service /arm (std_srvs/Trigger), or launch with arm:=true"


def _ms(age_s: float) -> str:
    return "ever" if math.isinf(age_s) else f"{age_s * 1000:.0f} ms"


def wheel_problem(state: DriveState) -> str:
    """Why the wheel of ``state`` cannot be driven, and what helps; "" when it can."""
    name = state.name
    if state.foreign_master:
        return (f"{name} is driven by another master ({state.foreign_master}): stop the other driver or bench tool;"
                " this driver configures it again once the bus is its own, then /arm")
    if state.lost:
        return (f"{name} is lost (no heartbeat for {_ms(state.heartbeat_age_s)}): check its power and CAN cable;"
                " it is configured again (disabled) when heard, then /arm")
    if state.stale:
        return (f"{name}'s data is stale (no PDO for {_ms(state.data_age_s)}): its bus or the drive is stalled;"
                " it is driven again once its PDOs are fresh (/arm does not help)")
    if state.state in FAULT_STATES:
        emcy = f", EMCY 0x{state.error_code:04X} {state.error_text}" if state.error_code else ""
        return f"{name} is in {state.state.name}{emcy}: clear it with the service {name}/recover, then /arm"
    if state.nmt != "OPERATIONAL":
        return f"{name} is in NMT {state.nmt}: it is configured again by the driver, then /arm"
    if not state.enabled:
        return f"{name} is not armed ({state.state.name}): {ARM}"
    return ""


def problems(states: Iterable[DriveState]) -> str:
    """The first wheel's problem, and how many more have one (with their names)."""
    said = [(s.name, wheel_problem(s)) for s in states]
    said = [(name, text) for name, text in said if text]
    if not said:
        return ""
    more = f" (and {len(said) - 1} more: {', '.join(n for n, _ in said[1:])})" if len(said) > 1 else ""
    return said[0][1] + more


def odometry_sample(state: DriveState) -> WheelSample:
    """What the odometry may take from a wheel: its position at the PDO's time and reference;
    not trusted while stale (its last sample kept: the reference says whether the next one
    follows from it), forgotten when lost or faulted."""
    trusted = not (state.lost or state.stale or state.fault or not state.stamp)
    keep = not (state.lost or state.fault)
    return WheelSample(math.radians(state.angle_deg), state.stamp, state.reference, trusted,
                       "" if trusted else _short(state), forget=not keep,
                       velocity_rad_s=math.radians(state.velocity_deg_s))


def _short(state: DriveState) -> str:
    if state.lost:
        return f"lost (no heartbeat for {_ms(state.heartbeat_age_s)})"
    if state.fault:
        return f"faulted ({state.state.name})"
    if state.stale:
        return f"stale (no PDO for {_ms(state.data_age_s)})"
    return "no position yet"


@dataclass
class OutWheel:
    reason: str
    seen_down: bool = False  # the drive has left Operation Enabled since it went out
    told: int = 0  # stops sent to it


class WheelsOut:
    """``on_wheel_loss: continue``: the wheels left out, each with its reason. A wheel goes out
    when it is lost, faulted, another master's or no longer enabled while the rover drives (one
    whose data is only late is not taken out: it still hears its side's commands); it comes back only once it has left
    Operation Enabled (stopped) and is enabled again (/arm, recover): never by itself, still
    running from before."""

    def __init__(self, left: Sequence[str], right: Sequence[str]) -> None:
        self.left, self.right = tuple(left), tuple(right)
        self.out: dict[str, OutWheel] = {}

    def update(self, states: dict[str, DriveState], driving: bool) -> tuple[list[str], list[str]]:
        """(wheels that went out now, wheels that came back now)."""
        went, back = [], []
        for name, state in states.items():
            out = self.out.get(name)
            if out is None:
                # out: lost, faulted, another master's, or no longer enabled; data that is only late
                # (stale: a stalled bus or host) does not take it out: it hears the commands
                if driving and not state.enabled and (state.lost or state.fault or state.foreign_master or
                                                      state.state != State.OPERATION_ENABLED):
                    self.out[name] = OutWheel(wheel_problem(state))
                    went.append(name)
                continue
            if state.state != State.OPERATION_ENABLED and not state.lost:
                out.seen_down = True
            if out.seen_down and state.enabled:
                del self.out[name]
                back.append(name)
        return went, back

    def still_running(self, states: dict[str, DriveState]) -> list[str]:
        """Wheels out that still run under their own steam (heard in Operation Enabled, not yet
        stopped): told to stop again."""
        return [n for n, o in self.out.items() if not o.seen_down and states[n].enabled]

    def share(self) -> float:
        """The share of wheels left on the weaker side (1.0: all; 0.0: a side has none)."""
        left = sum(1 for n in self.left if n not in self.out) / len(self.left)
        right = sum(1 for n in self.right if n not in self.out) / len(self.right)
        return min(left, right)

    def summary(self) -> str:
        return "; ".join(f"{n} out ({o.reason})" for n, o in self.out.items())

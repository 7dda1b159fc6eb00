"""One verdict per drive: what the driver knows of it, judged once (pure: no I/O, no clock).

:func:`judge` turns :class:`DriveFacts` (what the driver knows) into a :class:`Verdict` (a small
immutable value: the condition, the age of the data it rests on, the cause and what helps).
/diagnostics, the refusals of commands, odometry's trust, the drive system, MotorState and
/joint_states, the recorder and the bench CLI read the verdict; none of them combines flags of
its own.

The conditions, first match wins (the precedence):

1. ``another master``: another master drives it (its NMT or RPDO frames seen): commands refused.
2. ``lost``: no heartbeat within the consumer time.
3. ``re-booting``: it sent boot-up (reset or power cycle) and is being configured again.
4. ``not configured``: not booted (before the first boot, or a boot that failed).
5. ``late``: its data (TPDOs) is older than its staleness bound, or was never heard (an age that
   is infinite or not a number, whatever the bound): every value is old or absent.
6. ``faulted``: its statusword says FAULT or FAULT REACTION ACTIVE, or it reported FAULT since
   this driver last dealt with its faults (a fault that cleared itself still stops motion until
   recover and enable).
7. ``motion held``: the process holds every motion (a lifecycle node inactive); the reason says
   what lets it go ("rovercan_lifecycle is inactive: activate it").
8. ``out``: the drive system left it out (``on_wheel_loss: continue``) and told it to stop.
9. ``stopped itself``: it left Operation Enabled with no stop of this driver's (its host watch
   on host heartbeat loss, EMCY 0x8130; a limit; its own quick stop).
10. ``not armed``: not in Operation Enabled (never enabled, or stopped by this driver: who, why).
11. ``usable``: Operation Enabled with fresh data.

Precedence: what makes the data meaningless (another master, lost, a reset, never configured,
stale) comes before what the data says (fault, stopped), and what the driver did (out, a stop of
its own) before "not armed". Only ``usable`` may be driven or counted by odometry.

Where each input comes from, one writer each (:meth:`motor_driver.drive.DriveCache.facts` reads
them): the data's age, the statusword, the NMT state, the heartbeat's age and the EMCY are the
bus's receive thread's (:mod:`motor_driver.drive.received.state`; boot's NMT start is a field of its own
there), and so is ``fault_seen`` (the receive thread counts the FAULT statuswords; boot and the
command threads each acknowledge them in a field of their own); lost, booted, re-booting and another master are the supervisor's
(:mod:`motor_driver.runtime`); ``armed`` and ``stopped_by`` are the command channel's
(:mod:`motor_driver.drive.command.channel`, under its lock), and so is ``held`` (motion held: the
lifecycle node inactive); ``left_out`` is the drive system's control
loop's (``nodes/rover/drive_system.py``), which judges a copy of the facts with it set. A reader of a
recording judges the facts it rebuilds from the frames the same way (``judge(DriveFacts(...))``;
a :class:`motor_driver.drive.DriveState` made without them is judged from its own fields).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from enum import Enum
from typing import NamedTuple

from can_config.objects import EMCY_HEARTBEAT_LOST
from motor_driver.protocol.cia402 import FAULT_STATES, State
from motor_driver.protocol.pdo import TpdoLayout


class Condition(Enum):
    """A drive's condition; its value is what the rover says (diagnostics, refusals, MotorState)."""

    USABLE = "usable"
    LATE = "late"
    LOST = "lost"
    FAULTED = "faulted"
    STOPPED_ITSELF = "stopped itself"
    REBOOTING = "re-booting"
    NOT_CONFIGURED = "not configured"
    ANOTHER_MASTER = "another master"
    OUT = "out"
    HELD = "motion held"
    NOT_ARMED = "not armed"


#: The order :func:`judge` tries the conditions in (``usable`` last: nothing else holds).
PRECEDENCE = (Condition.ANOTHER_MASTER, Condition.LOST, Condition.REBOOTING, Condition.NOT_CONFIGURED,
              Condition.LATE, Condition.FAULTED, Condition.HELD, Condition.OUT, Condition.STOPPED_ITSELF,
              Condition.NOT_ARMED, Condition.USABLE)
#: Conditions in which a drive cannot hear or answer this driver: every command is refused.
UNREACHABLE = frozenset({Condition.ANOTHER_MASTER, Condition.LOST, Condition.REBOOTING, Condition.NOT_CONFIGURED})
#: What /arm (enable every drive) helps with.
ARM = "/arm enables it again"


class DriveFacts(NamedTuple):
    """What the driver knows of one drive; ages on the receive thread's monotonic clock (s).
    (A NamedTuple, not a frozen dataclass: it is made for every command checked, and a frozen
    dataclass's constructor cost ten times as much.)"""

    name: str
    data_age_s: float = math.inf  # since its data was last whole: every TPDO sent each SYNC heard (inf: never)
    stale_after_s: float = math.inf  # its staleness bound (stale_after_syncs SYNC periods)
    heartbeat_age_s: float = math.inf
    nmt: str = "UNKNOWN"
    state: State = State.NOT_READY_TO_SWITCH_ON
    lost: bool = False
    booted: bool = False
    rebooting: bool = False  # boot-up heard since it was operational, or configured again
    foreign_master: str = ""  # the evidence that another master drives it
    armed: bool = False  # this driver enabled it and sent no stop since
    enables: int = 0  # enables of this driver's that it completed (one who saw fewer has had one since)
    stopped_by: str = ""  # this driver's newest stop (who and why), "" none
    emcy_code: int = 0  # its newest EMCY not yet dealt with (0: none)
    emcy_text: str = ""
    emcy_stamp: float = 0.0  # the EMCY frame's wall-clock time (for people: "lost at 12:03:04")
    left_out: str = ""  # why the drive system left it out ("" it did not)
    held: str = ""  # why motion is held ("" it is not: the lifecycle node active, or no lifecycle)
    fault_seen: int = 0  # a FAULT statusword it reported since its faults were last dealt with (0: none)
    missing: str = ""  # late while other TPDOs of its are heard: those not heard ("TPDO 0x282 (0x6064, 0x606C)")


class Verdict(NamedTuple):
    """A drive's condition, the age of the data it rests on (s), the cause, and what helps."""

    name: str
    condition: Condition
    age_s: float
    cause: str
    helps: str = ""

    @property
    def usable(self) -> bool:
        """May be driven, and counted by odometry."""
        return self.condition is Condition.USABLE

    @property
    def fresh(self) -> bool:
        """Its values are news (published as measured); False: absent (NaN, the age said)."""
        return self.condition not in _NOT_MEASURED

    def text(self) -> str:
        """``<name>: <cause>; <what helps>``: what a refusal or a diagnostic says."""
        return f"{self.name}: {self.cause}" + (f"; {self.helps}" if self.helps else "")


_NOT_MEASURED = (UNREACHABLE - {Condition.ANOTHER_MASTER}) | {Condition.LATE}


def ms(age_s: float) -> str:
    """An age for people: ``240 ms``, or ``ever`` (never heard)."""
    return f"{age_s * 1000:.0f} ms" if age_s < math.inf else "ever"


def clock_text(stamp: float) -> str:
    """A wall-clock time of day (UTC) for people: ``12:03:04.250``."""
    return time.strftime("%H:%M:%S", time.gmtime(stamp)) + f".{int(stamp * 1000) % 1000:03d}" if stamp else "?"


def judge(facts: DriveFacts) -> Verdict:
    """The verdict on one drive: the first condition of :data:`PRECEDENCE` that holds."""
    f = facts
    age = f.data_age_s

    def say(condition: Condition, cause: str, helps: str = "") -> Verdict:
        return Verdict(f.name, condition, age, cause, helps)

    if f.foreign_master:
        return say(Condition.ANOTHER_MASTER, "not under this driver's control: another master is on the bus"
                   f" ({f.foreign_master})",
                   "stop the other driver or bench tool; this driver configures it again once the bus is its own,"
                   " then /arm")
    if f.lost:
        return say(Condition.LOST, f"heartbeat lost: none for {ms(f.heartbeat_age_s)}",
                   "check its power and CAN cable; it is configured again (disabled) when heard, then /arm")
    if f.rebooting:
        return say(Condition.REBOOTING, f"re-booting: it reset (NMT {f.nmt}) and is being configured again",
                   "wait for the re-configuration, then /arm")
    if not f.booted:
        return say(Condition.NOT_CONFIGURED, f"not configured (NMT {f.nmt})",
                   "boot it (the driver configures it once it answers), then /arm")
    if not (age < math.inf and age <= f.stale_after_s):  # never heard (inf, NaN) is late under any bound
        return _late(f)
    if f.state in FAULT_STATES:
        emcy = f": EMCY 0x{f.emcy_code:04X} {f.emcy_text}" if f.emcy_code else ""
        return say(Condition.FAULTED, f"faulted ({f.state.name}{emcy})", f"clear it with {f.name}/recover, then /arm")
    if f.fault_seen:
        return say(Condition.FAULTED, f"faulted: it reported FAULT (statusword 0x{f.fault_seen:04X}) since it was"
                   f" enabled, though it shows {f.state.name} now",
                   f"recover() and enable() it again ({f.name}/recover, then /arm)")
    if f.held:
        return say(Condition.HELD, "motion held", f.held)  # the holder's reason says what lets it go
    if f.left_out:
        return say(Condition.OUT, f"out of the drive system ({f.left_out})", "/arm takes it back once it is usable")
    enabled = f.state == State.OPERATION_ENABLED
    if not enabled and (f.armed or f.emcy_code == EMCY_HEARTBEAT_LOST):
        return say(Condition.STOPPED_ITSELF, _stopped_itself(f), ARM)
    if not enabled:
        by = f", stopped by {f.stopped_by}" if f.stopped_by else ""
        return say(Condition.NOT_ARMED, f"not armed ({f.state.name}{by})",
                   "arm the rover with the service /arm (std_srvs/Trigger), or launch with arm:=true")
    return say(Condition.USABLE, "usable")


def missing_tpdos(heard: Mapping[int, float], layouts: Mapping[int, TpdoLayout], *, now: float, bound: float) -> str:
    """The TPDOs sent every SYNC (``heard``: COB-ID -> its newest reception, 0.0 never) not heard
    within ``bound`` while another of them was, each with its objects; "" when none is missing
    or none was heard within it (a stalled bus or drive: no TPDO to name; a TPDO sent on a change
    says nothing of the others still coming). For :attr:`DriveFacts.missing`: the cache's and the
    bus view's alike."""
    if not any(now - at <= bound for at in heard.values()):
        return ""
    return ", ".join(f"TPDO 0x{cob:03X} ({', '.join(f'0x{i:04X}' for i in layouts[cob].indexes)})"
                     for cob, at in list(heard.items()) if not now - at <= bound)


def _late(f: DriveFacts) -> Verdict:
    age = f.data_age_s
    if f.missing:
        return Verdict(f.name, Condition.LATE, age, f"{f.missing} not heard for {ms(age)} while its other PDOs are"
                       " (lost on the bus, or the drive maps or sends it otherwise)",
                       "check the drive's PDO mapping, and the bus's error frames and load (/diagnostics); it is"
                       " usable again once that TPDO comes (/arm does not help)")
    return Verdict(f.name, Condition.LATE, age, f"no data for {ms(age)} (bus or drive stalled)",
                   "it is usable again once its data is fresh (/arm does not help)")


def _stopped_itself(f: DriveFacts) -> str:
    if f.emcy_code == EMCY_HEARTBEAT_LOST:
        return f"stopped itself: host heartbeat lost at {clock_text(f.emcy_stamp)} (EMCY 0x8130; now {f.state.name})"
    if f.emcy_code:
        return f"stopped itself: EMCY 0x{f.emcy_code:04X} {f.emcy_text} (now {f.state.name})"
    return f"stopped itself: it left Operation Enabled with no stop of this driver's (now {f.state.name})"

"""Clear rules that grade a drive's state as OK / WARN / ERROR (pure; the node turns the
result into diagnostic_msgs). A drive is graded from its verdict (:mod:`motor_driver.drive.verdict`,
carried by its snapshot), whose cause and what helps are the message; nothing here combines the
drive's flags again. The rules, first match wins:

* ERROR: its verdict is another master, lost, not configured, late, faulted or stopped itself
  (:data:`GRADE`); or a safety check read back after boot failed
  (:mod:`motor_driver.protocol.safety`: nothing would stop it if the host died, limits not set, ...).
* WARN: its verdict is re-booting (being configured again) or out (the drive system left it
  out); more of its TPDOs or heartbeats lost over the measured window than
  ``frame_loss_warn_percent`` (:mod:`motor_driver.diagnostics.frameloss`); a command was refused since the
  last report; the statusword warning bit is set; it has no drive-side stop on host loss and
  the config allows that (``allow_no_host_watch``).

Health grades buses and jobs by their own figures, and drives by their verdict: a lost bus is its
bus's status (:func:`bus_health`), and a drive on it is graded by what its verdict says of it
(late within a few SYNC periods, then lost); a heartbeat's age is the verdict's (lost, at the
consumer time), shown in the values, not graded again here.
* Frames of the drive a receive callback raised on (:func:`rejections`): ERROR while its data is
  late for it (the driver's decoding, not the bus), WARN while recent.
* OK: otherwise (usable, or not armed: safely disabled).

Frames of a drive that a receive callback raised on (:func:`rejections`): within
REJECTED_RECENT_S, ERROR when its data is stale (the driver's decoding, not the bus, is the
likely cause: said so), else WARN.

The driver's own work (:func:`jobs_health`): ERROR when the supervisor's loop ended (every drive
was told to stop); WARN while a background job failed unexpectedly within JOB_FAULT_RECENT_S (it
was retried); the counts per kind in the values either way.

A bus (:func:`bus_health`): ERROR when lost, down or BUS-OFF; WARN when its controller is
ERROR-WARNING or ERROR-PASSIVE, a frame was not sent for a full transmit queue, or its load is
over 50 %; its state and counters from the
kernel where it is a kernel interface (:mod:`motor_driver.bus.link`), "unknown" elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

from can_config.objects import emcy_text
from motor_driver.bus.adapters import Rejected
from motor_driver.bus.link import KernelBusHealth
from motor_driver.diagnostics.frameloss import Loss
from motor_driver.drive import DriveState
from motor_driver.drive.ledger import DriveRecord
from motor_driver.drive.verdict import Condition
from motor_driver.process.jobs import JOB_KINDS, JobFault
from motor_driver.protocol.cia402 import DRIVE_FUNCTION_ON, SW
from motor_driver.protocol.safety import ALLOWED, SafetyCheck

#: The levels of diagnostic_msgs/DiagnosticStatus: every grade on /diagnostics, the driver's and the
#: recorder's, is one of them (STALE: not heard at all).
OK, WARN, ERROR, STALE = 0, 1, 2, 3
#: A drive's rejected frames count in its grade for this long after the newest.
REJECTED_RECENT_S = 10.0
#: A background job's unexpected failure makes the driver's status WARN for this long.
JOB_FAULT_RECENT_S = 30.0

#: The level of each verdict (the rules above may raise it, never lower it).
GRADE = {Condition.USABLE: OK, Condition.NOT_ARMED: OK, Condition.HELD: OK, Condition.OUT: WARN, Condition.REBOOTING: WARN,
         Condition.ANOTHER_MASTER: ERROR, Condition.LOST: ERROR, Condition.NOT_CONFIGURED: ERROR,
         Condition.LATE: ERROR, Condition.FAULTED: ERROR, Condition.STOPPED_ITSELF: ERROR}


@dataclass(frozen=True)
class Health:
    level: int
    message: str
    values: dict[str, str]


class Rejections(NamedTuple):
    """Frames of a drive a receive callback raised on: how many, the newest's cause and age."""

    frames: int = 0
    cause: str = ""
    age_s: float = math.inf

    @classmethod
    def of(cls, rejected: Rejected | None, now: float) -> Rejections:
        """From the driver's count (``now``: the receive thread's monotonic clock)."""
        return cls() if rejected is None else cls(rejected.count, rejected.cause, now - rejected.at)


NO_REJECTIONS = Rejections()


def drive_health(state: DriveState, *, heartbeat_period_s: float, refused_since_last: int = 0,  # noqa: PLR0913
                 last_refusal: str = "", bus_lost: bool = False, tpdos_applied: int = 0,
                 safety: Sequence[SafetyCheck] = (), rejected: Rejections = NO_REJECTIONS,
                 frame_loss: Loss | None = None,
                 frame_loss_warn_percent: float = 100.0) -> Health:
    """One drive graded by the rules above; ``frame_loss``: its measured window (None: still
    measuring); ``rejected``: its frames a receive callback raised on. ``bus_lost`` and
    ``heartbeat_period_s`` are shown in the values, never graded (the module docstring)."""
    values = {
        "node_id": str(state.node_id),
        "nmt_state": state.nmt,
        "cia402_state": state.state.name,
        "statusword": f"0x{state.statusword:04X}",
        "mode": str(state.mode),
        "angle_deg": f"{state.angle_deg:.3f}",
        "velocity_deg_s": f"{state.velocity_deg_s:.3f}",
        "torque_nm": "n/a" if math.isnan(state.torque_nm) else f"{state.torque_nm:.3f}",
        "last_emcy_code": f"0x{state.error_code:04X}",
        "last_emcy_text": emcy_text(state.error_code) if state.error_code else "",
        "heartbeat_age_s": "never" if math.isinf(state.heartbeat_age_s) else f"{state.heartbeat_age_s:.3f}",
        "heartbeat_period_s": f"{heartbeat_period_s:g}",
        "bus": "lost" if bus_lost else "up",
        "refused_commands": str(refused_since_last),
        "tpdos_applied": str(tpdos_applied),
        "last_refusal": last_refusal,
    }
    for check in safety:
        values[f"safety: {check.check} ({check.object})"] = f"{check.status}: {check.actual}"
    failed, allowed = [c for c in safety if c.failed], [c for c in safety if c.status == ALLOWED]
    values["data_age_s"] = "never" if math.isinf(state.data_age_s) else f"{state.data_age_s:.3f}"
    values["foreign_master"] = state.foreign_master
    graded = rejections(state, values, rejected)  # its values whatever the grade
    verdict = state.verdict
    values["condition"] = verdict.condition.value
    values["frame_loss"] = frame_loss.text() if frame_loss is not None else "measuring"
    if graded is not None and graded.level == ERROR:
        return graded  # only late: because the driver rejected its frames, not the bus or the drive
    said = verdict.cause + (f"; {verdict.helps}" if verdict.helps else "")
    if GRADE[verdict.condition] == ERROR:
        return Health(ERROR, said, values)
    if failed:
        return Health(ERROR, "safety check failed: " + "; ".join(f"{c.check} ({c.object} is {c.actual},"
                                                                 f" expected {c.expected})" for c in failed), values)
    if graded is not None:
        return graded
    if GRADE[verdict.condition] == WARN:
        return Health(WARN, said, values)
    if verdict.condition is Condition.HELD and state.state in DRIVE_FUNCTION_ON:  # a hold's stop not confirmed
        return Health(WARN, f"motion held, yet still {state.state.name} (its stop not confirmed): {said}", values)
    if frame_loss is not None and frame_loss.worst_percent > frame_loss_warn_percent:
        return Health(WARN, f"frames lost: {frame_loss.text()} (over {frame_loss_warn_percent:g} %): check the"
                      " cabling, termination and bus load", values)
    if refused_since_last:
        return Health(WARN, f"{refused_since_last} command(s) refused: {last_refusal}", values)
    if state.statusword & SW.WARNING:
        return Health(WARN, "drive warning bit set", values)
    if allowed:
        return Health(WARN, "NO drive-side stop on host loss (allowed by allow_no_host_watch): if this process"
                      " dies while the drive is enabled, nothing stops it", values)
    return Health(OK, "enabled" if verdict.usable else f"ready: {verdict.cause}", values)


def rejections(state: DriveState, values: dict[str, str], rejected: Rejections) -> Health | None:
    """Frames of the drive a receive callback raised on: in ``values`` always; the grade while
    the newest is recent."""
    count, cause = rejected.frames, rejected.cause
    values["rejected_frames"] = str(count)
    values["last_rejection"] = cause
    if not count or rejected.age_s > REJECTED_RECENT_S:
        return None
    if state.verdict.condition is Condition.LATE:  # late because its frames were rejected, nothing worse
        return Health(ERROR, f"stale: {count} frame(s) from it rejected by the driver ({cause}): a fault in this"
                      " driver's decoding, not the bus; report it with the flight recorder's incident", values)
    return Health(WARN, f"{count} frame(s) from it rejected by the driver ({cause})", values)


#: Re-configurations of one drive that failed before its grade is ERROR (each is retried).
RECONFIGURE_FAILURES_ERROR = 3


def with_boot(health: Health, record: DriveRecord) -> Health:
    """A drive's grade with what its boots went through (the supervisor's ledger): restarts of a
    configuration, failed re-configurations and the times its heartbeat was overdue only because
    this driver had not read that far (Supervisor._read_behind) in its values; ERROR once re-configuration has
    failed RECONFIGURE_FAILURES_ERROR times, naming the newest error."""
    values = {**health.values, "boot_restarts": str(record.boot_restarts),
              "boot_restart_why": record.boot_restart_why, "reconfigure_failures": str(record.reconfigure_failures),
              "reconfigure_error": record.reconfigure_error,
              # heartbeats overdue while this driver's receive thread was behind: its lateness, not judged
              "heartbeat_read_behind": str(record.read_behind_episodes)}
    if record.reconfigure_failures >= RECONFIGURE_FAILURES_ERROR and health.level < ERROR:
        return Health(ERROR, f"re-configuration failed {record.reconfigure_failures} times ({record.reconfigure_error});"
                      " it is retried: check its power, wiring and EDS", values)
    return Health(health.level, health.message, values)


def jobs_health(faults: Mapping[str, JobFault], *, ended: str, alive: bool, now: float) -> Health:
    """The driver's own background work: the supervisor's loop (``alive``; ``ended``: why it
    ended on its own) and the unexpected failures of its jobs per kind (``now``: the clock of
    their ``at``)."""
    values = {kind: str(faults[kind].count if kind in faults else 0) for kind in (*JOB_KINDS, *faults)}
    newest = max(faults.values(), key=lambda f: f.at, default=None)
    values["last_failure"] = f"{newest.where}: {newest.cause}" if newest is not None else ""
    values["supervisor"] = "running" if alive else (ended or "not running")
    if ended:
        return Health(ERROR, ended, values)
    if not alive:
        return Health(ERROR, "the supervisor does not run: nothing watches the drives; restart the driver", values)
    if newest is not None and now - newest.at < JOB_FAULT_RECENT_S:
        return Health(WARN, f"{newest.where}: a {_kind_of(faults, newest)} failed unexpectedly ({newest.cause});"
                      " retried", values)
    return Health(OK, "supervisor running" + (f"; {sum(f.count for f in faults.values())} job failure(s) so far"
                                              if faults else ""), values)


def _kind_of(faults: Mapping[str, JobFault], fault: JobFault) -> str:
    return next(kind for kind, f in faults.items() if f is fault)


#: The kernel's figures a bus's status carries, where the kernel has them.
KERNEL_VALUES = ("state", "tx_errors", "rx_errors", "bitrate", "restart_ms", "restarts", "bus_off", "error_passive",
                 "error_warning", "bus_errors", "rx_dropped", "tx_dropped")


def bus_health(*, load: float, lost: bool, frames: int, error_frames: int,  # noqa: PLR0913 (one bus's figures)
               kernel: KernelBusHealth | None,
               why_unknown: str = "", tx_queue_full: int = 0, tx_not_sent: int = 0, rejected_frames: int = 0,
               frame_loss: Loss | None = None) -> Health:
    """One bus graded: lost, down or BUS-OFF is ERROR; ERROR-WARNING, ERROR-PASSIVE, a frame not
    sent for a full transmit queue or a load over 50 % is WARN. ``kernel``: what the kernel says
    (None: not a kernel interface, ``why_unknown``); ``tx_queue_full``: sends refused with ENOBUFS
    (each retried), ``tx_not_sent``: frames given up on; ``frame_loss``: its drives' frames lost,
    summed (:func:`motor_driver.diagnostics.frameloss.total`)."""
    values = {"load": f"{load:.4f}", "frames_received": str(frames), "error_frames": str(error_frames),
              "tx_queue_full": str(tx_queue_full), "tx_not_sent": str(tx_not_sent),
              "rejected_frames": str(rejected_frames),
              "frame_loss": frame_loss.text() if frame_loss is not None else "measuring"}
    if kernel is None:
        values["can_state"] = f"unknown ({why_unknown})" if why_unknown else "unknown"
    else:
        for key in KERNEL_VALUES:
            value = getattr(kernel, key)
            values["can_state" if key == "state" else key] = ("none (no controller)" if key == "state" else "unknown") \
                if value is None else str(value)
        values["link"] = "up" if kernel.link_up else "down"
    problems = kernel.problems() if kernel is not None else []
    if lost:
        return Health(ERROR, "bus lost", values)
    if kernel is not None and (not kernel.link_up or kernel.state == "BUS-OFF"):
        return Health(ERROR, "; ".join(problems), values)
    if tx_not_sent:
        problems.append(f"{tx_not_sent} frame(s) not sent: the transmit queue stayed full (ENOBUFS); check that"
                        " the drives acknowledge (cabling, termination, bitrate)")
    if problems:
        return Health(WARN, "; ".join(problems), values)
    if load > 0.5:
        return Health(WARN, f"load {load:.1%}", values)
    return Health(OK, f"load {load:.1%}" + (f", {kernel.state}" if kernel is not None and kernel.state else ""), values)

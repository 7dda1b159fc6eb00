"""Clear rules that grade a drive's state as OK / WARN / ERROR (pure; the node turns the
result into diagnostic_msgs). The rules:

* ERROR: the drive is lost (no heartbeat within the consumer time), in FAULT or FAULT
  REACTION ACTIVE, its bus is lost, another master drives it, its PDOs stopped while it is
  operational (stale data), or a safety check read back after boot failed
  (:mod:`motor_driver.protocol.safety`: nothing would stop it if the host died, limits not set, ...).
* WARN: the statusword warning bit is set, a command was refused since the last report,
  the heartbeat is older than 1.5 producer periods, the drive is not booted, or it has no
  drive-side stop on host loss and the config allows that (``allow_no_host_watch``).
* OK: otherwise (enabled or safely disabled).

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

from can_config.objects import emcy_text
from motor_driver.bus.adapters import Rejected
from motor_driver.bus.link import KernelBusHealth
from motor_driver.drive import DriveState
from motor_driver.process.jobs import JOB_KINDS, JobFault
from motor_driver.protocol.cia402 import FAULT_STATES, SW
from motor_driver.protocol.safety import ALLOWED, SafetyCheck

OK, WARN, ERROR = 0, 1, 2
#: A drive's rejected frames count in its grade for this long after the newest.
REJECTED_RECENT_S = 10.0
#: A background job's unexpected failure makes the driver's status WARN for this long.
JOB_FAULT_RECENT_S = 30.0


@dataclass(frozen=True)
class Health:
    level: int
    message: str
    values: dict[str, str]


def drive_health(state: DriveState, *, heartbeat_period_s: float, refused_since_last: int = 0,
                 last_refusal: str = "", bus_lost: bool = False, tpdos_applied: int = 0,
                 safety: Sequence[SafetyCheck] = (), rejected: Rejected | None = None,
                 rejected_age_s: float = math.inf) -> Health:
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
        "refused_commands": str(refused_since_last),
        "tpdos_applied": str(tpdos_applied),
        "last_refusal": last_refusal,
    }
    for check in safety:
        values[f"safety: {check.check} ({check.object})"] = f"{check.status}: {check.actual}"
    failed = [c for c in safety if c.failed]
    allowed = [c for c in safety if c.status == ALLOWED]
    values["data_age_s"] = "never" if math.isinf(state.data_age_s) else f"{state.data_age_s:.3f}"
    values["foreign_master"] = state.foreign_master
    graded = rejections(state, values, rejected, rejected_age_s)  # its values whatever the grade
    if bus_lost:
        return Health(ERROR, "bus lost", values)
    if state.foreign_master:
        return Health(ERROR, f"not under control: another master on the bus ({state.foreign_master})", values)
    if state.lost:
        return Health(ERROR, f"heartbeat lost ({values['heartbeat_age_s']} s): check the drive's power and CAN cable;"
                      " it is configured again (disabled) when heard, then arm it", values)
    if state.state in FAULT_STATES:
        code = state.error_code
        return Health(ERROR, f"fault: EMCY 0x{code:04X} {emcy_text(code)}" if code else "fault", values)
    if failed:
        return Health(ERROR, "safety check failed: " + "; ".join(f"{c.check} ({c.object} is {c.actual},"
                                                                 f" expected {c.expected})" for c in failed), values)
    if graded is not None:
        return graded
    if state.stale and state.nmt == "OPERATIONAL":
        return Health(ERROR, f"stale: no PDO for {values['data_age_s']} s; the values shown are old (its bus or"
                      " this host is stalled: arming does not help)", values)
    if refused_since_last:
        return Health(WARN, f"{refused_since_last} command(s) refused: {last_refusal}", values)
    if state.statusword & SW.WARNING:
        return Health(WARN, "drive warning bit set", values)
    if state.heartbeat_age_s > 1.5 * heartbeat_period_s:
        return Health(WARN, f"heartbeat late ({values['heartbeat_age_s']} s)", values)
    if allowed:
        return Health(WARN, "NO drive-side stop on host loss (allowed by allow_no_host_watch): if this process"
                      " dies while the drive is enabled, nothing stops it", values)
    return Health(OK, "enabled" if state.enabled else f"ready ({state.state.name})", values)


def rejections(state: DriveState, values: dict[str, str], rejected: Rejected | None, age_s: float) -> Health | None:
    """Frames of the drive a receive callback raised on (the newest ``age_s`` ago): in
    ``values`` always; the grade while the newest is recent."""
    count, cause = (rejected.count, rejected.cause) if rejected is not None else (0, "")
    values["rejected_frames"] = str(count)
    values["last_rejection"] = cause
    if not count or age_s > REJECTED_RECENT_S:
        return None
    if state.stale:
        return Health(ERROR, f"stale: {count} frame(s) from it rejected by the driver ({cause}): a fault in this"
                      " driver's decoding, not the bus; report it with the flight recorder's incident", values)
    return Health(WARN, f"{count} frame(s) from it rejected by the driver ({cause})", values)


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


def bus_health(*, load: float, lost: bool, frames: int, error_frames: int, kernel: KernelBusHealth | None,
               why_unknown: str = "", tx_queue_full: int = 0, tx_not_sent: int = 0, rejected_frames: int = 0) -> Health:
    """One bus graded: lost, down or BUS-OFF is ERROR; ERROR-WARNING, ERROR-PASSIVE, a frame not
    sent for a full transmit queue or a load over 50 % is WARN. ``kernel``: what the kernel says
    (None: not a kernel interface, ``why_unknown``); ``tx_queue_full``: sends refused with ENOBUFS
    (each retried), ``tx_not_sent``: frames given up on."""
    values = {"load": f"{load:.4f}", "frames_received": str(frames), "error_frames": str(error_frames),
              "tx_queue_full": str(tx_queue_full), "tx_not_sent": str(tx_not_sent),
              "rejected_frames": str(rejected_frames)}
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

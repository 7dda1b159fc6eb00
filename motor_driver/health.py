"""Clear rules that grade a drive's state as OK / WARN / ERROR (pure; the node turns the
result into diagnostic_msgs). A drive is graded from its verdict (:mod:`motor_driver.verdict`,
carried by its snapshot), whose cause and what helps are the message; nothing here combines the
drive's flags again. The rules, first match wins:

* ERROR: its bus is lost; its verdict is another master, lost, not configured, late, faulted or
  stopped itself (:data:`GRADE`); or a safety check read back after boot failed
  (:mod:`motor_driver.safety`: nothing would stop it if the host died, limits not set, ...).
* WARN: its verdict is re-booting (being configured again) or out (the drive system left it
  out); more of its TPDOs or heartbeats lost over the measured window than
  ``frame_loss_warn_percent`` (:mod:`motor_driver.frameloss`); a command was refused since the
  last report; the statusword warning bit is set; the heartbeat is older than 1.5 producer
  periods; it has no drive-side stop on host loss and the config allows that
  (``allow_no_host_watch``).
* OK: otherwise (usable, or not armed: safely disabled).

A bus (:func:`bus_health`): ERROR when lost, down or BUS-OFF; WARN when its controller is
ERROR-WARNING or ERROR-PASSIVE, a frame was not sent for a full transmit queue, or its load is
over 50 %; its state and counters from the
kernel where it is a kernel interface (:mod:`motor_driver.bushealth`), "unknown" elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from can_config.objects import emcy_text
from motor_driver.bushealth import KernelBusHealth
from motor_driver.cia402 import SW
from motor_driver.drive import DriveState
from motor_driver.frameloss import Loss
from motor_driver.safety import ALLOWED, SafetyCheck
from motor_driver.verdict import Condition

OK, WARN, ERROR = 0, 1, 2

#: The level of each verdict (the rules above may raise it, never lower it).
GRADE = {Condition.USABLE: OK, Condition.NOT_ARMED: OK, Condition.OUT: WARN, Condition.REBOOTING: WARN,
         Condition.ANOTHER_MASTER: ERROR, Condition.LOST: ERROR, Condition.NOT_CONFIGURED: ERROR,
         Condition.LATE: ERROR, Condition.FAULTED: ERROR, Condition.STOPPED_ITSELF: ERROR}


@dataclass(frozen=True)
class Health:
    level: int
    message: str
    values: dict[str, str]


def drive_health(state: DriveState, *, heartbeat_period_s: float, refused_since_last: int = 0,
                 last_refusal: str = "", bus_lost: bool = False, tpdos_applied: int = 0,
                 safety: Sequence[SafetyCheck] = (), frame_loss: Loss | None = None,
                 frame_loss_warn_percent: float = 100.0) -> Health:
    """One drive graded by the rules above; ``frame_loss``: its measured window (None: still measuring)."""
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
    verdict = state.verdict
    values["condition"] = verdict.condition.value
    values["frame_loss"] = frame_loss.text() if frame_loss is not None else "measuring"
    if bus_lost:
        return Health(ERROR, "bus lost", values)
    said = verdict.cause + (f"; {verdict.helps}" if verdict.helps else "")
    if GRADE[verdict.condition] == ERROR:
        return Health(ERROR, said, values)
    if failed:
        return Health(ERROR, "safety check failed: " + "; ".join(f"{c.check} ({c.object} is {c.actual},"
                                                                 f" expected {c.expected})" for c in failed), values)
    if GRADE[verdict.condition] == WARN:
        return Health(WARN, said, values)
    if frame_loss is not None and frame_loss.worst_percent > frame_loss_warn_percent:
        return Health(WARN, f"frames lost: {frame_loss.text()} (over {frame_loss_warn_percent:g} %): check the"
                      " cabling, termination and bus load", values)
    if refused_since_last:
        return Health(WARN, f"{refused_since_last} command(s) refused: {last_refusal}", values)
    if state.statusword & SW.WARNING:
        return Health(WARN, "drive warning bit set", values)
    if state.heartbeat_age_s > 1.5 * heartbeat_period_s:
        return Health(WARN, f"heartbeat late ({values['heartbeat_age_s']} s)", values)
    if allowed:
        return Health(WARN, "NO drive-side stop on host loss (allowed by allow_no_host_watch): if this process"
                      " dies while the drive is enabled, nothing stops it", values)
    return Health(OK, "enabled" if verdict.usable else f"ready: {verdict.cause}", values)


#: The kernel's figures a bus's status carries, where the kernel has them.
KERNEL_VALUES = ("state", "tx_errors", "rx_errors", "bitrate", "restart_ms", "restarts", "bus_off", "error_passive",
                 "error_warning", "bus_errors", "rx_dropped", "tx_dropped")


def bus_health(*, load: float, lost: bool, frames: int, error_frames: int, kernel: KernelBusHealth | None,
               why_unknown: str = "", tx_queue_full: int = 0, tx_not_sent: int = 0,
               frame_loss: Loss | None = None) -> Health:
    """One bus graded: lost, down or BUS-OFF is ERROR; ERROR-WARNING, ERROR-PASSIVE, a frame not
    sent for a full transmit queue or a load over 50 % is WARN. ``kernel``: what the kernel says
    (None: not a kernel interface, ``why_unknown``); ``tx_queue_full``: sends refused with ENOBUFS
    (each retried), ``tx_not_sent``: frames given up on; ``frame_loss``: its drives' frames lost,
    summed (:func:`motor_driver.frameloss.total`)."""
    values = {"load": f"{load:.4f}", "frames_received": str(frames), "error_frames": str(error_frames),
              "tx_queue_full": str(tx_queue_full), "tx_not_sent": str(tx_not_sent),
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

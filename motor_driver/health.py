"""Clear rules that grade a drive's state as OK / WARN / ERROR (pure; the node turns the
result into diagnostic_msgs). The rules:

* ERROR: the drive is lost (no heartbeat within the consumer time), in FAULT or FAULT
  REACTION ACTIVE, or its bus is lost.
* WARN: the statusword warning bit is set, a command was refused since the last report,
  the heartbeat is older than 1.5 producer periods, or the drive is not booted.
* OK: otherwise (enabled or safely disabled).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from can_config.objects import emcy_text
from motor_driver.cia402 import SW, State
from motor_driver.drive import DriveState

OK, WARN, ERROR = 0, 1, 2


@dataclass(frozen=True)
class Health:
    level: int
    message: str
    values: dict[str, str]


def drive_health(state: DriveState, *, heartbeat_period_s: float, refused_since_last: int = 0,
                 last_refusal: str = "", bus_lost: bool = False, tpdos_applied: int = 0) -> Health:
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
    if bus_lost:
        return Health(ERROR, "bus lost", values)
    if state.lost:
        return Health(ERROR, f"heartbeat lost ({values['heartbeat_age_s']} s)", values)
    if state.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
        code = state.error_code
        return Health(ERROR, f"fault: EMCY 0x{code:04X} {emcy_text(code)}" if code else "fault", values)
    if refused_since_last:
        return Health(WARN, f"{refused_since_last} command(s) refused: {last_refusal}", values)
    if state.statusword & SW.WARNING:
        return Health(WARN, "drive warning bit set", values)
    if state.heartbeat_age_s > 1.5 * heartbeat_period_s:
        return Health(WARN, f"heartbeat late ({values['heartbeat_age_s']} s)", values)
    return Health(OK, "enabled" if state.enabled else f"ready ({state.state.name})", values)

"""The values the state cache publishes: immutable, replaced whole, safe to read from any thread."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from motor_driver.protocol.cia402 import State


@dataclass(frozen=True)
class Emcy:
    code: int
    register: int
    text: str
    timestamp: float


@dataclass(frozen=True)
class DriveState:
    """A snapshot of what the driver knows about one drive, in engineering units."""

    name: str
    node_id: int
    angle_deg: float
    velocity_deg_s: float
    torque_nm: float  # NaN where the drive has no torque actual value (0x6077)
    statusword: int
    state: State
    mode: int
    nmt: str
    enabled: bool
    fault: bool
    lost: bool
    error_code: int
    error_text: str
    stamp: float  # time.time() when the PDOs carrying this state arrived
    heartbeat_age_s: float
    target_reached: bool
    data_age_s: float = math.inf  # since the last TPDO arrived
    stale: bool = False  # no TPDO for stale_after_syncs SYNC periods: the values above are old
    foreign_master: str = ""  # evidence that another master drives it: commands are refused
    reference: int = 0  # the position reference (boot, homing, a reboot's jump start a new one)


class Received(NamedTuple):
    """What the TPDOs said last: replaced whole by the receive thread."""

    statusword: int = 0
    mode: int = 0
    position_counts: int = 0
    velocity_counts_s: int = 0
    torque_permille: float = math.nan
    stamp: float = 0.0  # time.time() of the frame
    rx_monotonic: float = 0.0  # when it arrived
    reference: int = 0  # the position reference it belongs to (PositionFilter.reference)


class StatusSink(Protocol):
    """The command channel, as the receive thread sees it."""

    def on_status(self, acknowledged: bool) -> None: ...

    def enabled_by_us(self, now: float, within_s: float) -> bool: ...

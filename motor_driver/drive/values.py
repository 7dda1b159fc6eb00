"""The values the state cache publishes: immutable, replaced whole, safe to read from any thread.

A :class:`DriveState` is a drive's face: its verdict and the values published with it, made from
one read of what the drive said (one :class:`Received`). It offers no flags (enabled, fault, lost,
stale, held): whether a drive may be driven, is measured, faulted or lost is its ``verdict``
(:mod:`motor_driver.drive.verdict`), and a reader reads that and nothing else. One made by hand
(a recording's, a test's) carries the facts it was judged from (``judged``), or is judged from
its values as a booted drive heard by nobody else, with the same rule for data never heard (an
infinite age: never usable).
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field
from typing import Any, NamedTuple, Protocol

from motor_driver.drive.verdict import DriveFacts, Verdict, judge
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
    error_code: int
    error_text: str
    stamp: float  # time.time() when the PDOs carrying this state arrived
    heartbeat_age_s: float
    target_reached: bool
    data_age_s: float = math.inf  # since its data was last whole (``whole_rx``)
    foreign_master: str = ""  # evidence that another master drives it: commands are refused
    reference: int = 0  # the position reference (boot, homing, a reboot's jump start a new one)
    rx_monotonic: float = 0.0  # when the PDOs carrying this state arrived (monotonic; 0.0 never)
    #: when ``angle_deg`` was measured (``stamp``'s clock) and received (``rx_monotonic``'s): its own
    #: TPDO's, which a later TPDO without a position (torque, a statusword on change) does not move;
    #: 0.0 no position TPDO yet. What the odometry takes a sample's time and newness from.
    position_stamp: float = 0.0
    position_rx: float = 0.0
    #: when its data was last whole (Received.whole_rx: what ``data_age_s`` counts from; 0.0 never)
    whole_rx: float = 0.0
    #: the facts and verdict the driver judged (the snapshot's); None: judged from the values
    #: above (a snapshot made by hand, a test's or a recording's, and every dataclasses.replace)
    judged: InitVar[tuple[DriveFacts, Verdict] | None] = None
    #: what the driver knows of it, and the one judgement of it every consumer reads
    facts: DriveFacts = field(init=False, compare=False)
    verdict: Verdict = field(init=False, compare=False)

    def __post_init__(self, judged: tuple[DriveFacts, Verdict] | None) -> None:
        if judged is None:  # judged from its own values: a data age that is infinite (never heard) is late
            facts = DriveFacts(self.name, data_age_s=self.data_age_s, heartbeat_age_s=self.heartbeat_age_s,
                               nmt=self.nmt, state=self.state, booted=True, foreign_master=self.foreign_master,
                               emcy_code=self.error_code, emcy_text=self.error_text)
            judged = facts, judge(facts)
        object.__setattr__(self, "facts", judged[0])
        object.__setattr__(self, "verdict", judged[1])

    @classmethod
    def judged_as(cls, facts: DriveFacts, verdict: Verdict, **values: Any) -> DriveState:
        """The driver's own snapshot (:meth:`DriveCache.snapshot`, once per new frame or SYNC
        period): ``values`` are every field of the class, set in one step rather than one
        ``object.__setattr__`` each as a frozen dataclass's ``__init__`` does (3 us against 13-15
        in isolation; benchmarks/hotpath.py's ``tpdo_then_snapshot_us``). The same object
        otherwise: equal to ``DriveState(**values, judged=(facts, verdict))``, frozen, replaceable
        (tests/test_verdict_once.py holds a real snapshot to the class's fields; mypy does not see
        the names and types of ``values``)."""
        state = object.__new__(cls)
        state.__dict__.update(values, facts=facts, verdict=verdict)
        return state


class Received(NamedTuple):
    """What the TPDOs said last: replaced whole by the receive thread."""

    statusword: int = 0
    mode: int = 0
    position_counts: int = 0
    velocity_counts_s: int = 0
    torque_permille: float = math.nan
    stamp: float = 0.0  # when measured: a SYNC TPDO's SYNC, else the frame (bus stamp, time.time()'s clock)
    rx_monotonic: float = 0.0  # when it arrived
    reference: int = 0  # the position reference it belongs to (PositionFilter.reference)
    noted_at: float = 0.0  # the SDO note (Noted.at) its values carry already (0.0: none)
    #: the position's own ``stamp`` and ``rx_monotonic``: of the TPDO that carried it, not of the
    #: newest frame (a SYNC's torque TPDO after its position TPDO; a statusword sent on change)
    position_stamp: float = 0.0
    position_rx: float = 0.0
    #: when the data was last whole (monotonic; 0.0 never): the oldest of the newest receptions of
    #: each TPDO sent every SYNC (one of them lost, its values are old however fresh the others'), or
    #: with none sent every SYNC the newest TPDO's; what the data's age is judged from
    whole_rx: float = 0.0


@dataclass(frozen=True)
class Noted:
    """What an SDO read found (boot's seed, a confirmed mode switch): laid over the TPDOs' values
    until the receive thread carries it into the next :class:`Received` (``noted_at``). A field of
    its own, so that the reader of the SDO never writes the receive thread's value."""

    at: float  # when it was read (monotonic): its identity
    statusword: int | None = None
    position_counts: int | None = None
    mode: int | None = None

    def over(self, rx: Received) -> Received:
        if rx.noted_at == self.at:
            return rx  # carried already: the TPDOs' newer values stand
        sw = rx.statusword if self.statusword is None else self.statusword
        position = rx.position_counts if self.position_counts is None else self.position_counts
        mode = rx.mode if self.mode is None else self.mode
        return rx._replace(statusword=sw, position_counts=position, mode=mode, noted_at=self.at)


class StatusSink(Protocol):
    """The command channel, as the receive thread sees it."""

    def on_status(self, acknowledged: bool) -> None: ...

    def enabled_by_us(self, now: float, within_s: float) -> bool: ...

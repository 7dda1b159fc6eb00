"""The simulated drive's fixed parts: CiA 402 states and bits, the pure state transition,
the motor model's parameters, a PDO's layout and the fault-injection switches.

No state of its own (dataclasses owned by the drive that holds them).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field

from can_config.config import SimModelConfig
from can_config.objects import Cia402State, OperationMode
from virtual_can.sim.objects import ObjectStore

logger = logging.getLogger(__name__)


#: CiA 402 power states: the names are can_config's passive definition; their statusword coding
#: (below) and the state machine are the simulator's own reading of the standard.
State = Cia402State


#: Statusword bits 0-3, 5, 6 for each state (CiA 402 table 30).
STATUS_BITS: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}

#: Longest integration step of the motor model.
PHYSICS_STEP_S = 0.001
#: How far past a software position limit the shaft may go before the drive faults: a servo
#: that reaches a set-point at the limit at speed overshoots it (0.4-0.75 deg at the joint for a
#: 100 deg/s stream stopped in one cycle through a 50:1 gear, 0.1 motor rev); a real excursion
#: goes on.
LIMIT_TOLERANCE_REV = 0.25
#: A cyclic position set-point older than this is held (no velocity fed forward from it).
CYCLIC_GAP_S = 0.1
#: A SYNC's actual values are the plant's at the SYNC's moment, moved on from the last physics tick
#: at the shaft's speed (a tick is 2 ms, the SYNC falls anywhere in it), by at most this much (a
#: runner held for longer has not simulated the time in between: its next tick catches up)
LATCH_AHEAD_MAX_S = 0.01
#: The bus's stamps against the runner's clock: a handling delay of a SYNC further than this from the
#: least seen is a clock step (the offset starts anew); the least may rise this much per second of bus
#: time (the wall clock's slew against the monotonic one: NTP slews at most 0.5 ms/s)
BUS_CLOCK_STEP_S = 0.2
BUS_OFFSET_SLEW = 1.0e-3

#: 0x1010 "save" signature ("save" in ASCII, little endian) and what each sub-index stores.
SAVE_SIGNATURE = int.from_bytes(b"save", "little")
SAVE_RANGES = {1: (0x1000, 0x9FFF), 2: (0x1000, 0x1FFF), 3: (0x6000, 0x9FFF), 4: (0x2000, 0x5FFF)}
#: A real drive writes its flash meanwhile: its SDO server answers the save this much later.
SAVE_SILENCE_S = 0.4
#: EMCY codes (CiA 301 / CiA 402; a lost heartbeat producer or guard is can_config's EMCY_HEARTBEAT_LOST).
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_STO = 0x5441  # safe torque off (the drive's enable input low)
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_POSITION_LIMIT = 0x8612  # reference limit (software position limit)

SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_OMS12 = 1 << 12  # PP: setpoint acknowledge; PV: speed; homing: attained; CSP: following; IP: active
SW_OMS13 = 1 << 13  # PP/CSP: following error; homing: homing error

CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low
CW_ENABLE_OPERATION = 1 << 3
CW_NEW_SETPOINT = 1 << 4  # homing: start
CW_CHANGE_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8

POWERED = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
#: the quick-stop options (0x605A) after whose ramp the drive stays in Quick Stop Active, halted
#: (5: the slow-down ramp, 6: the quick-stop ramp, 7: the current limit, 8: the voltage limit; 1-4
#: the same ramps, then Switch On Disabled)
QUICK_STOP_HOLDS = frozenset({5, 6, 7, 8})
#: a set-point speed below this (counts/s) is standstill: a power stage switched off then cuts no ramp
STANDSTILL_COUNTS_S = 1.0
VELOCITY_MODES = (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY)
ENABLING = (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED)
ERROR_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}  # by code's first nibble


def next_state(state: State, cw: int, prev_cw: int, *, voltage_ok: bool,  # noqa: C901, PLR0911, PLR0912
               quick_stop_option: int) -> State:
    """The CiA 402 transition a controlword causes (pure; transition numbers in comments). One
    branch per transition of the standard's table, in its order: the complexity is the table's."""
    if state == State.FAULT:
        if cw & CW_FAULT_RESET and not prev_cw & CW_FAULT_RESET:
            return State.SWITCH_ON_DISABLED  # 15
        return state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return state
    ev = bool(cw & CW_ENABLE_VOLTAGE)
    qs = not cw & CW_QUICK_STOP
    so = bool(cw & CW_SWITCH_ON)
    eo = bool(cw & CW_ENABLE_OPERATION)
    shutdown = ev and not qs and not so
    switch_on = ev and not qs and so
    if state == State.SWITCH_ON_DISABLED:
        return State.READY_TO_SWITCH_ON if shutdown else state  # 2
    if state == State.READY_TO_SWITCH_ON:
        if not ev or qs:
            return State.SWITCH_ON_DISABLED  # 7
        if switch_on and voltage_ok:
            return State.OPERATION_ENABLED if eo else State.SWITCHED_ON  # 3 (+4)
        return state
    if state == State.SWITCHED_ON:
        if not ev or qs:
            return State.SWITCH_ON_DISABLED  # 10
        if shutdown:
            return State.READY_TO_SWITCH_ON  # 6
        if switch_on and eo:
            return State.OPERATION_ENABLED  # 4
        return state
    if state == State.OPERATION_ENABLED:
        if not ev:
            return State.SWITCH_ON_DISABLED  # 9
        if qs:
            return State.QUICK_STOP_ACTIVE  # 11
        if shutdown:
            return State.READY_TO_SWITCH_ON  # 8
        if switch_on and not eo:
            return State.SWITCHED_ON  # 5
        return state
    if state == State.QUICK_STOP_ACTIVE:
        if not ev:
            return State.SWITCH_ON_DISABLED  # 12
        if switch_on and eo and quick_stop_option in QUICK_STOP_HOLDS:
            return State.OPERATION_ENABLED  # 16
        return state
    return state


@dataclass
class MotorParams:
    """Physical model of the motor, its gear and its load, all on the motor side of the gear,
    and the drive's servo loops.

    The defaults look like one wheel of a ~60 kg six-wheeled rover behind a 50:1 gear: rotor
    plus reflected wheel and body inertia 1e-4 kg m^2, gear and rolling friction 0.03 Nm,
    a 1 ms current loop, a 50 Hz velocity loop and a position loop at a tenth of it.
    """

    #: the encoder's increments per motor revolution; None: the EDS's 0x608F, else 4096. Given, it is
    #: also what the drive reports in 0x608F (a real drive reports its own encoder there)
    counts_per_rev: int | None = None
    inertia_kg_m2: float = 1e-4
    viscous_nm_s_rad: float = 2e-5
    coulomb_nm: float = 0.03  # dry friction: opposes motion; at rest it holds up to this torque
    load_nm: float = 0.0  # external load (a slope), opposing positive motion
    rated_torque_nm: float = 1.0  # used when the EDS has no 0x6076
    torque_lag_s: float = 0.001  # time constant of the current (torque) loop
    bandwidth_hz: float = 50.0  # velocity loop; the gains below default to it
    position_kp: float | None = None  # 1/s: velocity asked per position error
    velocity_kp: float | None = None  # Nm s/rad
    velocity_ki: float | None = None  # Nm/rad
    velocity_ff: float = 1.0  # the profile's velocity fed forward into the velocity loop
    index_position_counts: int = 0  # where homing finds its switch/index

    @classmethod
    def from_model(cls, model: SimModelConfig, counts_per_rev: int | None = None) -> MotorParams:
        """The model of a drive's ``sim:`` section of the rover config."""
        return cls(counts_per_rev=counts_per_rev, inertia_kg_m2=model.inertia_kg_m2,
                   viscous_nm_s_rad=model.viscous_nm_s_rad, coulomb_nm=model.coulomb_nm, load_nm=model.load_nm,
                   torque_lag_s=model.torque_lag_s, bandwidth_hz=model.bandwidth_hz,
                   position_kp=model.position_kp, velocity_kp=model.velocity_kp,
                   velocity_ki=model.velocity_ki, velocity_ff=model.velocity_ff)

    def gains(self) -> tuple[float, float, float]:
        """(position kp 1/s, velocity kp Nm s/rad, velocity ki Nm/rad)."""
        wv = 2 * math.pi * self.bandwidth_hz
        kv = self.velocity_kp if self.velocity_kp is not None else self.inertia_kg_m2 * wv
        ki = self.velocity_ki if self.velocity_ki is not None else kv * wv / 4.0
        kp = self.position_kp if self.position_kp is not None else wv / 10.0
        return kp, kv, ki


@dataclass
class Pdo:
    cob_id: int
    trans_type: int
    entries: list[tuple[int, int, str]]  # (index, subindex, struct format)
    inhibit_s: float = 0.0
    event_s: float = 0.0
    sync_count: int = 0
    last_data: bytes | None = None
    last_sent: float = -1e9

    def pack(self, store: ObjectStore) -> bytes:
        values = store.values
        return b"".join(struct.pack(fmt, values[(i, s)]) for i, s, fmt in self.entries)


@dataclass
class Faults:
    """Fault-injection switches of one drive."""

    unplugged: bool = False
    tpdo_silent: bool = False  # heartbeat and SDO go on, no TPDO leaves (a PDO set lost, a stuck stack)
    lost_tpdos: frozenset[int] = frozenset()  # the COB-IDs of the TPDOs that no longer leave (its others do)
    tx_dead: bool = False  # it receives and acts, sends nothing (a broken TX line, a hung CAN task)
    guard_toggle_stuck: bool = False  # its node-guarding answers keep toggle bit 0
    heartbeat_deaf: bool = False  # it no longer hears others' heartbeats: its consumer (host watch) trips
    sto_low: bool = False
    sdo_delay_s: float = 0.0
    #: its synchronous TPDOs leave this long after the SYNC's moment, plus a random 0..sync_jitter_s
    #: each SYNC, still carrying what it latched at the SYNC (CiA 301), and every frame of its own
    #: in the order it made them (one transmit queue): a slow drive, or a busy bus's arbitration
    sync_delay_s: float = 0.0
    sync_jitter_s: float = 0.0
    #: an EMCY code it detects in the cycle of its next SYNC, after its synchronous TPDOs latched:
    #: that cycle's frames leave by identifier (its transmit buffers' CAN arbitration), so the
    #: EMCY and the statusword's event TPDO pass the synchronous TPDOs latched before the fault
    latched_fault: int = 0
    ack_delay_max_s: float = 0.0  # the set-point acknowledge comes after a random delay up to this
    enable_step_delay_s: float = 0.0  # each enabling transition (2, 3, 4) takes this long
    power_off_until: float = 0.0
    stalled: bool = False  # the shaft is blocked (a wheel jammed against a rock): it cannot turn
    cw_per_cycle: bool = False  # event RPDOs taken once per cycle, the last of each (many drives)
    #: it resets itself (NMT reset node: objects back to their saved or EDS values, boot-up) at the
    #: n-th SDO write from when this is set, then at the n-th write after that reset for the next
    #: entry, and so on (a brown-out or a watchdog in the middle of a master's configuration)
    reset_at_writes: list[int] = field(default_factory=list)
    reset_at_object: tuple[int, int | None] | None = None  # ... or at the next write to (index, sub; None: any)
    reset_answers: bool = True  # the write that resets it is answered first (False: the answer is lost)
    reset_bootup: bool = True  # it sends its boot-up after that reset (False: the frame is lost)
    reset_pending: bool = False  # a write asked for the reset: it follows that write's answer
    garbled_statusword: bool = False  # its statusword's state bits show no CiA 402 state (broken firmware)
    #: a velocity mode's "speed reached" (bit 10) stays set through its quick-stop ramp (some vendors'):
    #: bit 10 alone then says nothing of standstill
    speed_reached_in_quick_stop: bool = False
    #: what its quick stop does whatever 0x605A says (a firmware that ignores it; reads of 0x605A still
    #: return what was written, so a master cannot see it); None: 0x605A
    quick_stop_option: int | None = None
    pending: list[int] = field(default_factory=list)  # EMCY codes to raise at the next tick

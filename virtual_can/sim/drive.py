"""A simulated CiA 402 servo drive, written from CiA 301 / CiA 402 on its own.

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
"""

from __future__ import annotations

import logging
import math
import random
import struct
from dataclasses import dataclass, field
from enum import IntEnum

import can
from canopen.objectdictionary import ObjectDictionary

from can_config.config import SimModelConfig
from can_config.objects import (
    OD,
    PDO_COB_ID_INVALID,
    STRUCT_FORMAT,
    NmtCommand,
    NmtState,
    OperationMode,
)
from virtual_can.sim.objects import (
    ABORT_DEVICE_STATE,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
    ObjectStore,
    SdoAbort,
)
from virtual_can.sim.sdo import SdoServer

logger = logging.getLogger(__name__)


class State(IntEnum):
    """CiA 402 power state machine states (the simulator's own definition)."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


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

#: EMCY codes (CiA 301 / CiA 402).
#: 0x1010 "save" signature ("save" in ASCII, little endian) and what each sub-index stores.
SAVE_SIGNATURE = int.from_bytes(b"save", "little")
SAVE_RANGES = {1: (0x1000, 0x9FFF), 2: (0x1000, 0x1FFF), 3: (0x6000, 0x9FFF), 4: (0x2000, 0x5FFF)}
#: A real drive writes its flash meanwhile: its SDO server answers the save this much later.
SAVE_SILENCE_S = 0.4
EMCY_HEARTBEAT = 0x8130  # life guard error or heartbeat error
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
ENABLING = (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED)
ERROR_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}  # by code's first nibble


def next_state(state: State, cw: int, prev_cw: int, *, voltage_ok: bool, quick_stop_option: int) -> State:
    """The CiA 402 transition a controlword causes (pure; transition numbers in comments)."""
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
        if switch_on and eo and quick_stop_option >= 5:
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
class _Pdo:
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
    sto_low: bool = False
    sdo_delay_s: float = 0.0
    ack_delay_max_s: float = 0.0  # the set-point acknowledge comes after a random delay up to this
    enable_step_delay_s: float = 0.0  # each enabling transition (2, 3, 4) takes this long
    power_off_until: float = 0.0
    stalled: bool = False  # the shaft is blocked (a wheel jammed against a rock): it cannot turn
    cw_per_cycle: bool = False  # event RPDOs taken once per cycle, the last of each (many drives)
    pending: list[int] = field(default_factory=list)  # EMCY codes to raise at the next tick


class SimulatedDrive:
    """One simulated CiA 402 node. Not thread-safe: driven by one runner thread."""

    def __init__(self, node_id: int, od: ObjectDictionary, params: MotorParams | None = None,
                 *, name: str | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node_id={node_id}: CANopen node ids are 1..127")
        self.node_id = node_id
        self.name = name or f"drive{node_id}"
        self.params = params or MotorParams()
        self._gains = self.params.gains()
        self.store = ObjectStore(od)
        self.store.on_write = self._on_sdo_write
        self.sdo = SdoServer(self.store)
        self.faults = Faults()
        self._now = 0.0
        #: every profile-position target the drive accepted, in order (None: not recorded)
        self.accepted_targets: list[float] | None = None
        self.nmt = NmtState.BOOTUP
        self.counters = {"tpdo": 0, "rpdo": 0, "emcy": 0, "sdo": 0}
        self._report_encoder()
        self._units_from_od()
        self._reset_node(now=0.0, announce=False)

    def _report_encoder(self) -> None:
        """0x608F holds the motor model's encoder, when the model was given one: its value after
        every reset, as a real drive reports the encoder it has."""
        cpr = self.params.counts_per_rev
        keys = ((OD.POSITION_ENCODER_RESOLUTION, 1), (OD.POSITION_ENCODER_RESOLUTION, 2))
        if cpr is None or not all(self.store.has(*key) for key in keys):
            return
        for key, value in zip(keys, (cpr, 1), strict=True):
            self.store.vars[key].default = value
            self.store.set(*key, value)

    def _units_from_od(self) -> None:
        """The drive's own units, from its factor group and SI velocity unit (CiA 402).

        Position: increments of the encoder (0x608F, when not 1:1, else the motor model's
        counts per rev), or feed units when the feed constant (0x6092) is not 1:1
        (feed per shaft revolution, shaft = motor / gear 0x6091). Velocity: position units/s,
        or 10^prefix motor rev/min (or /s) when 0x60A9 says so (maxon EPOS4: rpm).
        """
        store = self.store

        def ratio(index: int) -> float:
            num, den = store.get(index, 1, 0), store.get(index, 2, 0)
            return float(num) / float(den) if num and den else 1.0  # type: ignore[arg-type]

        enc, gear, feed = ratio(OD.POSITION_ENCODER_RESOLUTION), ratio(OD.GEAR_RATIO), ratio(OD.FEED_CONSTANT)
        increments = enc if enc != 1.0 else float(self.params.counts_per_rev or 4096)
        self.units_per_motor_rev = feed / gear if feed != 1.0 else increments
        self._rad_per_count = 2 * math.pi / self.units_per_motor_rev
        self._vconv = 1.0  # position units/s per velocity unit
        si = int(store.get(OD.SI_UNIT_VELOCITY, 0, 0))  # type: ignore[arg-type]
        if si and (si >> 16) & 0xFF == 0xB4:  # revolutions per ...
            prefix = (si >> 24) & 0xFF
            prefix = prefix - 256 if prefix >= 128 else prefix
            per = 60.0 if (si >> 8) & 0xFF == 0x47 else 1.0
            self._vconv = self.units_per_motor_rev * 10.0**prefix / per

    def _v(self, index: int, sub: int = 0, default: float = 0.0) -> float:
        """A velocity or acceleration object, in position units/s (or /s^2)."""
        return float(self.store.get(index, sub, default)) * self._vconv  # type: ignore[arg-type]

    # ---------------------------------------------------------------- lifecycle
    def _reset_node(self, now: float, announce: bool = True) -> list[can.Message]:
        self.store.reset(0x0000, 0xFFFF)
        self._reset_motion()
        return self._reset_comm(now, announce)

    def _reset_motion(self) -> None:
        self.state = State.SWITCH_ON_DISABLED
        self.prev_cw = 0
        self.theta = getattr(self, "theta", 0.0)  # the shaft does not move on a reset
        self.omega = 0.0
        self.torque_nm = 0.0
        self._vel_integral = 0.0
        self.sp_pos = self.theta / self._rad_per_count
        self.sp_vel = 0.0
        self.sp_acc = 0.0
        self.position_offset = getattr(self, "position_offset", 0.0)
        self.pp_target: float | None = None
        self.homing_active = False
        self.homing_done = False
        self.homing_error = False
        self.following_since: float | None = None
        self._csp_last: float | None = None
        self._csp_t = 0.0
        self._csp_from = 0.0  # the cyclic set-point being left, and the cycle it is left over
        self._csp_period = 1e-3
        self._last_sync = -1.0
        self._sync_period_s = 0.01  # measured from the SYNCs (a drive's 0x1006 / 0x60C2)
        self.error_code = 0
        self._pending_rpdos: list[tuple[_Pdo, bytes]] = []
        self._cycle_rpdos: list[tuple[_Pdo, bytes]] = []  # faults.cw_per_cycle: read at the tick
        self._setpoint_ack = False
        self._ack_at = 0.0  # the acknowledge shows from then on (fault injection: a slow drive)
        self._slow_transition: tuple[State, float] | None = None  # (state, when) of a slow enabling step
        self._pending_emcy_reset = False
        self._delayed_sdo: tuple[float, bytes] | None = None
        self._homing_start = 0.0

    def _reset_comm(self, now: float, announce: bool) -> list[can.Message]:
        self.store.reset(0x1000, 0x1FFF)
        self.nmt = NmtState.PRE_OPERATIONAL
        self._consumer_seen: dict[int, float] = {}  # 0x1016 sub -> when its producer was last heard
        self._guard_toggle = 0  # node guarding: the toggle bit of the next answer (0 after a reset)
        self._guarded_at: float | None = None  # the last guard; life guarding armed by the first one
        self._load_consumers()
        self._rebuild_pdos()
        self._next_heartbeat = now
        if not announce:
            return []
        return [self._msg(0x700 + self.node_id, b"\x00")]

    def power_cycle(self, now: float, off_s: float) -> None:
        """Fault injection: power off for ``off_s``, then boot again (boot-up message)."""
        self.faults.power_off_until = now + off_s
        self.state = State.NOT_READY_TO_SWITCH_ON

    # ---------------------------------------------------------------- PDO config
    def _rebuild_pdos(self) -> None:
        self.rpdos: dict[int, _Pdo] = {}
        self.tpdos: list[_Pdo] = []
        for n in range(512):
            comm, mapping = OD.RPDO_COMM + n, OD.RPDO_MAP + n
            if not self.store.has(comm, 1):
                break
            pdo = self._pdo(comm, mapping)
            if pdo is not None:
                self.rpdos[pdo.cob_id] = pdo
        for n in range(512):
            comm, mapping = OD.TPDO_COMM + n, OD.TPDO_MAP + n
            if not self.store.has(comm, 1):
                break
            pdo = self._pdo(comm, mapping)
            if pdo is not None:
                pdo.inhibit_s = int(self.store.get(comm, 3, 0)) * 100e-6  # type: ignore[arg-type]
                pdo.event_s = int(self.store.get(comm, 5, 0)) / 1000.0  # type: ignore[arg-type]
                self.tpdos.append(pdo)

    def _pdo(self, comm: int, mapping: int) -> _Pdo | None:
        cob = int(self.store.get(comm, 1, PDO_COB_ID_INVALID))  # type: ignore[arg-type]
        if cob & PDO_COB_ID_INVALID:
            return None
        entries = []
        count = int(self.store.get(mapping, 0, 0))  # type: ignore[arg-type]
        for sub in range(1, count + 1):
            raw = int(self.store.get(mapping, sub, 0))  # type: ignore[arg-type]
            index, subindex = raw >> 16, (raw >> 8) & 0xFF
            var = self.store.vars.get((index, subindex))
            fmt = STRUCT_FORMAT.get(var.data_type) if var is not None else None
            if var is None or fmt is None:
                logger.warning("node %d: PDO 0x%04X maps 0x%04X:%d, which it cannot carry;"
                               " PDO disabled", self.node_id, mapping, index, subindex)
                return None
            entries.append((index, subindex, fmt))
        return _Pdo(cob & 0x1FFFFFFF, int(self.store.get(comm, 2, 255)), entries)  # type: ignore[arg-type]

    def _check_mapping_write(self, index: int, subindex: int) -> None:
        """CiA 301 procedure: a mapping changes only while the PDO is invalid and sub 0 is 0."""
        comm = index - 0x200
        cob = int(self.store.get(comm, 1, 0))  # type: ignore[arg-type]
        if not cob & PDO_COB_ID_INVALID:
            raise SdoAbort(ABORT_DEVICE_STATE, index, subindex,
                           "set bit 31 of the PDO COB-ID before changing its mapping")
        if subindex == 0:
            count = int(self.store.get(index, 0))  # type: ignore[arg-type]
            bits = 0
            for sub in range(1, count + 1):
                raw = int(self.store.get(index, sub, 0))  # type: ignore[arg-type]
                var = self.store.vars.get((raw >> 16, (raw >> 8) & 0xFF))
                if var is None:
                    raise SdoAbort(0x0602_0000, index, subindex,
                                   f"mapped object 0x{raw >> 16:04X} does not exist")
                if not var.mappable:
                    raise SdoAbort(ABORT_NOT_MAPPABLE, index, subindex,
                                   f"0x{var.index:04X} cannot be PDO-mapped")
                bits += raw & 0xFF
            if bits > 64:
                raise SdoAbort(ABORT_PDO_LENGTH, index, subindex, f"{bits} bits > 64")
        elif int(self.store.get(index, 0)) != 0:  # type: ignore[arg-type]
            raise SdoAbort(ABORT_DEVICE_STATE, index, subindex,
                           "set sub-index 0 to 0 before changing mapping entries")

    def _store_parameters(self, subindex: int) -> None:
        """0x1010:sub = "save" (CiA 301): keep the values that a reset or power cycle restores."""
        if int(self.store.get(OD.STORE_PARAMETERS, subindex, 0)) != SAVE_SIGNATURE:  # type: ignore[arg-type]
            return
        low, high = SAVE_RANGES.get(subindex, (0x1000, 0x9FFF))
        kept = self.store.save(low, high)
        self.store.set(OD.STORE_PARAMETERS, subindex, 1)  # reads back its capability: saves on command
        logger.info("node %d: %d parameters saved (0x1010:%d)", self.node_id, kept, subindex)

    def _on_sdo_write(self, index: int, subindex: int) -> None:
        if 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF:
            self._check_mapping_write(index, subindex)
            self._rebuild_pdos()
        elif 0x1400 <= index <= 0x15FF or 0x1800 <= index <= 0x19FF:
            self._rebuild_pdos()
        elif index == OD.CONTROLWORD:
            self._apply_controlword()
        elif index == OD.MODES_OF_OPERATION:
            self._set_mode()
        elif index in (OD.TARGET_POSITION, OD.INTERPOLATION_DATA):
            self._csp_target()
        elif index == OD.CONSUMER_HEARTBEAT_TIME:
            self._consumer_seen.pop(subindex, None)  # a new entry is armed by its next heartbeat
            self._load_consumers()
        elif index == OD.STORE_PARAMETERS:
            self._store_parameters(subindex)

    # ---------------------------------------------------------------- heartbeat consumer
    def _load_consumers(self) -> None:
        """The active 0x1016 entries: sub -> (watched node id, consumer time in s)."""
        self._consumers: dict[int, tuple[int, float]] = {}
        for (index, sub), value in self.store.values.items():
            if index == OD.CONSUMER_HEARTBEAT_TIME and sub > 0 and isinstance(value, int):
                node, time_ms = (value >> 16) & 0x7F, value & 0xFFFF
                if node and time_ms:
                    self._consumers[sub] = (node, time_ms / 1000.0)

    def _on_heartbeat(self, node: int, now: float) -> None:
        for sub, (watched, _) in self._consumers.items():
            if watched == node:
                self._consumer_seen[sub] = now

    def _check_consumers(self, now: float) -> list[can.Message]:
        out: list[can.Message] = []
        for sub, (node, timeout_s) in self._consumers.items():
            seen = self._consumer_seen.get(sub)
            if seen is not None and now - seen > timeout_s:
                del self._consumer_seen[sub]  # disarmed until that producer is heard again
                logger.warning("node %d: heartbeat of node %d lost (consumer time %.0f ms)", self.node_id,
                               node, timeout_s * 1000)
                out += self._connection_lost(now)
        return out

    # ---------------------------------------------------------------- node guarding
    def _on_guard(self, now: float) -> list[can.Message]:
        """CiA 301 node guarding, the slave's side: answer toggle bit + NMT state; the first
        guard arms life guarding."""
        answer = self._guard_toggle << 7 | int(self.nmt)
        self._guard_toggle ^= 1
        self._guarded_at = now
        return [self._msg(0x700 + self.node_id, bytes([answer]))]

    def _check_life_guard(self, now: float) -> list[can.Message]:
        """Life guarding: no guard for guard time x life time factor (0x100C x 0x100D, both set)
        is a lost master: EMCY 0x8130 and the 0x6007 reaction, as for a heartbeat consumer."""
        guard_ms = int(self.store.get(OD.GUARD_TIME, 0, 0))  # type: ignore[arg-type]
        factor = int(self.store.get(OD.LIFE_TIME_FACTOR, 0, 0))  # type: ignore[arg-type]
        if self._guarded_at is None or not guard_ms or not factor or now - self._guarded_at <= guard_ms * factor / 1000:
            return []
        self._guarded_at = None  # disarmed until the next guard
        logger.warning("node %d: life guarding event (no guard for %d ms x %d)", self.node_id, guard_ms, factor)
        return self._connection_lost(now)

    def _connection_lost(self, now: float) -> list[can.Message]:
        """CiA 402 0x6007: the drive's own reaction to losing its master. A drive without 0x6007
        reacts as its vendor decided; the model takes the common choice, a fault."""
        option = int(self.store.get(OD.ABORT_CONNECTION_OPTION, 0, 1))  # type: ignore[arg-type]
        if option == 1:
            return self._raise_fault(EMCY_HEARTBEAT, now)
        if option == 2 and self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, *POWERED):
            self.state = State.SWITCH_ON_DISABLED
        elif option == 3:
            if self.state == State.OPERATION_ENABLED:
                self.state = State.QUICK_STOP_ACTIVE
            elif self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
                self.state = State.SWITCH_ON_DISABLED
        return [self._warning_emcy(EMCY_HEARTBEAT)]

    def _warning_emcy(self, code: int) -> can.Message:
        """An EMCY that reports an error without a fault state (communication error bit set)."""
        self._record_error(code)
        self.counters["emcy"] += 1
        return self._emcy(code, 0x11)

    # ---------------------------------------------------------------- frames in
    def on_frame(self, msg: can.Message, now: float) -> list[can.Message]:
        if self.faults.unplugged or now < self.faults.power_off_until or msg.is_extended_id:
            return []  # CANopen (CiA 301) uses 11-bit identifiers only
        if msg.is_remote_frame:  # the one remote frame CANopen uses: the master's node guard
            return self._on_guard(now) if msg.arbitration_id == 0x700 + self.node_id else []
        cob = msg.arbitration_id
        data = bytes(msg.data)
        if cob == 0:
            return self._on_nmt(data, now)
        if 0x701 <= cob <= 0x77F and cob != 0x700 + self.node_id and data:
            self._on_heartbeat(cob - 0x700, now)
            return []
        if cob == (int(self.store.get(OD.COB_ID_SYNC, 0, 0x80)) & 0x7FF):  # type: ignore[arg-type]
            return self._on_sync(now)
        if self.nmt == NmtState.STOPPED:
            return []
        if cob == 0x600 + self.node_id:
            saving = len(data) >= 4 and data[0] & 0xE0 == 0x20 and data[1:3] == OD.STORE_PARAMETERS.to_bytes(2, "little")
            if self.faults.sdo_delay_s > 0 or saving:  # a save keeps the drive's SDO server silent a while
                self._delayed_sdo = (now + max(self.faults.sdo_delay_s, SAVE_SILENCE_S if saving else 0.0), data)
                return []
            return self._sdo(data)
        pdo = self.rpdos.get(cob)
        if pdo is not None and self.nmt == NmtState.OPERATIONAL:
            self.counters["rpdo"] += 1
            if 0 <= pdo.trans_type <= 240:
                self._pending_rpdos.append((pdo, data))
            elif self.faults.cw_per_cycle:  # the drive reads its objects at its next cycle
                self._cycle_rpdos.append((pdo, data))
            else:  # taken at once, and the statusword answers at once (a drive's next cycle)
                self._apply_rpdo(pdo, data)
                self._now = now
                self._update_status()
                return [] if self.faults.unplugged else self._event_tpdos(now)
        return []

    def _sdo(self, data: bytes) -> list[can.Message]:
        self.counters["sdo"] += 1
        resp = self.sdo.handle(data)
        return [self._msg(0x580 + self.node_id, resp)] if resp is not None else []

    def _on_nmt(self, data: bytes, now: float) -> list[can.Message]:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return []
        cmd = data[0]
        if cmd == NmtCommand.START:
            self.nmt = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            self.nmt = NmtState.STOPPED
        elif cmd == NmtCommand.ENTER_PREOPERATIONAL:
            self.nmt = NmtState.PRE_OPERATIONAL
        elif cmd == NmtCommand.RESET_NODE:
            return self._reset_node(now)
        elif cmd == NmtCommand.RESET_COMMUNICATION:
            return self._reset_comm(now, announce=True)
        return []

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        self._act_on(self._write_rpdo(pdo, data))

    def _write_rpdo(self, pdo: _Pdo, data: bytes) -> set[int]:
        """The RPDO's values into the object dictionary; returns the objects written."""
        need = sum(struct.calcsize(fmt) for _, _, fmt in pdo.entries)
        if len(data) < need:
            self.faults.pending.append(0x8210)  # PDO not processed due to length error
            return set()
        offset = 0
        for index, sub, fmt in pdo.entries:
            (value,) = struct.unpack_from(fmt, data, offset)
            offset += struct.calcsize(fmt)
            self.store.values[(index, sub)] = value
        return {index for index, _, _ in pdo.entries}

    def _act_on(self, written: set[int]) -> None:
        """What the drive does with newly written objects (once per frame, or once per cycle)."""
        if OD.MODES_OF_OPERATION in written:
            self._set_mode()
        if OD.CONTROLWORD in written:
            self._apply_controlword()
        elif written & {OD.TARGET_POSITION, OD.INTERPOLATION_DATA}:
            self._csp_target()

    def _event_tpdos(self, now: float) -> list[can.Message]:
        """Event-driven TPDOs (254/255) whose data changed, or whose event timer is due."""
        out: list[can.Message] = []
        for pdo in self.tpdos:
            if pdo.trans_type >= 254:
                due = pdo.event_s and now - pdo.last_sent >= pdo.event_s
                if now - pdo.last_sent >= pdo.inhibit_s:
                    data = pdo.pack(self.store)
                    if due or data != pdo.last_data:
                        out += self._send_pdo(pdo, data, now)
        return out

    def _on_sync(self, now: float) -> list[can.Message]:
        interval = now - self._last_sync
        self._last_sync = now
        if 0.0005 < interval < CYCLIC_GAP_S:  # the cycle the cyclic modes interpolate over
            self._sync_period_s += 0.2 * (interval - self._sync_period_s)
        if self.nmt != NmtState.OPERATIONAL:
            return []
        for pdo, data in self._pending_rpdos:
            self._apply_rpdo(pdo, data)
        self._pending_rpdos.clear()
        out = []
        for pdo in self.tpdos:
            tt = pdo.trans_type
            if tt == 0:
                data = pdo.pack(self.store)
                if data != pdo.last_data:
                    out += self._send_pdo(pdo, data, now)
            elif 1 <= tt <= 240:
                pdo.sync_count += 1
                if pdo.sync_count >= tt:
                    pdo.sync_count = 0
                    out += self._send_pdo(pdo, pdo.pack(self.store), now)
        return out

    def _send_pdo(self, pdo: _Pdo, data: bytes, now: float) -> list[can.Message]:
        if self.faults.tpdo_silent:
            return []
        pdo.last_data = data
        pdo.last_sent = now
        self.counters["tpdo"] += 1
        return [self._msg(pdo.cob_id, data)]

    # ---------------------------------------------------------------- CiA 402
    def _apply_controlword(self) -> None:
        cw = int(self.store.get(OD.CONTROLWORD, 0))  # type: ignore[arg-type]
        new = next_state(self.state, cw, self.prev_cw, voltage_ok=not self.faults.sto_low,
                         quick_stop_option=int(self.store.get(OD.QUICK_STOP_OPTION, 0, 2)))  # type: ignore[arg-type]
        pending, self._slow_transition = self._slow_transition, None  # a new controlword overrides it
        if new != self.state:
            if self.faults.enable_step_delay_s > 0 and new in ENABLING and self.state in (State.SWITCH_ON_DISABLED,
                                                                                        *ENABLING):
                self._slow_transition = pending if pending is not None and pending[0] == new else \
                    (new, self._now + self.faults.enable_step_delay_s)  # a slow drive
            else:
                self._enter(new)
        mode = self.mode
        rising = cw & ~self.prev_cw
        if self.state == State.OPERATION_ENABLED:
            if mode == OperationMode.PROFILE_POSITION and rising & CW_NEW_SETPOINT:
                self._new_pp_setpoint(cw)
            elif mode == OperationMode.HOMING and rising & CW_NEW_SETPOINT:
                self._start_homing()
            elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
                self._csp_target()
        self.prev_cw = cw

    def _enter(self, new: State) -> None:
        if self.state == State.FAULT:
            self._clear_error()
        if new == State.OPERATION_ENABLED and self.state != State.QUICK_STOP_ACTIVE:
            self._hold_position()
        self.state = new

    @property
    def mode(self) -> int:
        return int(self.store.get(OD.MODES_OF_OPERATION_DISPLAY, 0))  # type: ignore[arg-type]

    def _set_mode(self) -> None:
        requested = int(self.store.get(OD.MODES_OF_OPERATION, 0))  # type: ignore[arg-type]
        supported = int(self.store.get(OD.SUPPORTED_DRIVE_MODES, 0, 0))  # type: ignore[arg-type]
        bit = {1: 0, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}.get(requested)
        if requested != 0 and (bit is None or not supported >> bit & 1):
            return  # unsupported: the display keeps the old mode, as real drives do
        self.store.set(OD.MODES_OF_OPERATION_DISPLAY, 0, requested)
        self.pp_target = None
        self.homing_active = False
        self._hold_position()

    def _hold_position(self) -> None:
        self.sp_pos = self.position_counts
        self.sp_vel = 0.0
        self.sp_acc = 0.0
        self.pp_target = None
        self._csp_last = None
        self._vel_integral = 0.0

    def _new_pp_setpoint(self, cw: int) -> None:
        target = float(self.store.get(OD.TARGET_POSITION, 0))  # type: ignore[arg-type]
        if cw & CW_RELATIVE:
            target += self.pp_target if self.pp_target is not None else self.sp_pos
        self.pp_target = target
        self._setpoint_ack = True
        if self.faults.ack_delay_max_s > 0:
            self._ack_at = self._now + random.uniform(0.0, self.faults.ack_delay_max_s)
        if self.accepted_targets is not None:
            self.accepted_targets.append(target)

    def _csp_target(self) -> None:
        """CSP: follow 0x607A; IP: follow 0x60C1:1 while controlword bit 4 (enable ip) is set."""
        if self.state != State.OPERATION_ENABLED:
            return
        if self.mode == OperationMode.CYCLIC_SYNC_POSITION:
            self.pp_target = float(self.store.get(OD.TARGET_POSITION, 0))  # type: ignore[arg-type]
        elif self.mode == OperationMode.INTERPOLATED_POSITION and self._ip_enabled:
            self.pp_target = float(self.store.get(OD.INTERPOLATION_DATA, 1, 0))  # type: ignore[arg-type]

    @property
    def _ip_enabled(self) -> bool:
        return bool(int(self.store.get(OD.CONTROLWORD, 0)) & CW_NEW_SETPOINT)  # type: ignore[arg-type]

    def _start_homing(self) -> None:
        method = int(self.store.get(OD.HOMING_METHOD, 0, 35))  # type: ignore[arg-type]
        self.homing_done = self.homing_error = False
        if method in (35, 37):
            self._home_here()
        else:
            self.homing_active = True
            self._homing_start = self.position_counts

    def _home_here(self) -> None:
        raw = self.theta / self._rad_per_count
        self.position_offset = -raw
        self.homing_active = False
        self.homing_done = True
        self._hold_position()

    # ---------------------------------------------------------------- faults
    def raise_fault(self, code: int) -> None:
        """Fault injection: the drive detects an error with this EMCY code at its next tick."""
        self.faults.pending.append(code)

    def _raise_fault(self, code: int, now: float | None) -> list[can.Message]:
        self.error_code = code
        self.store.set(OD.ERROR_CODE, 0, code)
        register = 0x01 | ERROR_REGISTER_BITS.get(code >> 12, 0)
        if code >> 8 == 0x86 or code >> 8 == 0x85:
            register |= 0x20  # device profile specific
        self.store.set(OD.ERROR_REGISTER, 0, register)
        self._record_error(code)
        if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self.state = State.FAULT_REACTION_ACTIVE if self.state in POWERED else State.FAULT
        self.counters["emcy"] += 1
        return [self._emcy(code, register)]

    def _record_error(self, code: int) -> None:
        """Push ``code`` onto the pre-defined error field (0x1003), newest at sub 1."""
        if self.store.has(OD.PREDEFINED_ERROR_FIELD, 1):
            depth = sum(1 for k in self.store.vars if k[0] == OD.PREDEFINED_ERROR_FIELD and k[1] > 0)
            for sub in range(depth, 1, -1):
                self.store.set(OD.PREDEFINED_ERROR_FIELD, sub, self.store.get(OD.PREDEFINED_ERROR_FIELD, sub - 1))
            self.store.set(OD.PREDEFINED_ERROR_FIELD, 1, code)
            count = int(self.store.get(OD.PREDEFINED_ERROR_FIELD, 0))  # type: ignore[arg-type]
            self.store.set(OD.PREDEFINED_ERROR_FIELD, 0, min(depth, count + 1))

    def _clear_error(self) -> None:
        self.error_code = 0
        self.store.set(OD.ERROR_CODE, 0, 0)
        self.store.set(OD.ERROR_REGISTER, 0, 0)
        self._pending_emcy_reset = True

    def _emcy(self, code: int, register: int) -> can.Message:
        cob = int(self.store.get(OD.COB_ID_EMCY, 0, 0x80 + self.node_id)) & 0x7FF  # type: ignore[arg-type]
        return self._msg(cob, struct.pack("<HB5x", code, register))

    # ---------------------------------------------------------------- time
    def tick(self, now: float, dt: float) -> list[can.Message]:
        """Advance the simulation by ``dt`` seconds; return the frames the drive sends."""
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
            out += self._raise_fault(0x5441, now)
        if self._consumer_seen:
            out += self._check_consumers(now)
        if self._guarded_at is not None:
            out += self._check_life_guard(now)
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
        out += self._move(now, dt)
        out += self._check_position_limits(now)
        self._update_status()
        if self.faults.unplugged:
            return []
        if self.nmt == NmtState.OPERATIONAL:
            out += self._event_tpdos(now)
        period_ms = int(self.store.get(OD.PRODUCER_HEARTBEAT_TIME, 0, 0))  # type: ignore[arg-type]
        if period_ms and now >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + period_ms / 1000.0, now)
            out.append(self._msg(0x700 + self.node_id, bytes([self.nmt])))
        return out

    @property
    def position_counts(self) -> float:
        return self.theta / self._rad_per_count + self.position_offset

    def _move(self, now: float, dt: float) -> list[can.Message]:
        store = self.store
        p = self.params
        k = self._rad_per_count
        powered = self.state in POWERED
        halt = bool(int(store.get(OD.CONTROLWORD, 0)) & CW_HALT)  # type: ignore[arg-type]
        mode = self.mode
        rated = float(store.get(OD.RATED_TORQUE, 0, 0)) / 1000.0 if store.has(OD.RATED_TORQUE) else 0.0  # type: ignore[arg-type]
        rated = rated or p.rated_torque_nm
        out: list[can.Message] = []
        if powered:
            decel = self._v(OD.PROFILE_DECELERATION, 0, 16384) or 16384.0
            accel = self._v(OD.PROFILE_ACCELERATION, 0, 16384) or 16384.0
            vmax = self._v(OD.PROFILE_VELOCITY, 0, 4096) or 4096.0
            vlimit = self._v(OD.MAX_PROFILE_VELOCITY, 0, 0) or vmax
            vmax = min(vmax, vlimit)
            if self.state != State.OPERATION_ENABLED:
                qs_decel = self._v(OD.QUICK_STOP_DECELERATION, 0, 65536) or 65536.0
                self._ramp_velocity(0.0, qs_decel, qs_decel, dt)
                if abs(self.sp_vel) < 1e-6:
                    self.state = State.FAULT if self.state == State.FAULT_REACTION_ACTIVE else State.SWITCH_ON_DISABLED
            elif halt and mode in (OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY,
                                   OperationMode.HOMING):
                self._ramp_velocity(0.0, decel, decel, dt)
            elif mode == OperationMode.PROFILE_POSITION and self.pp_target is not None:
                self._track_position(self.pp_target, vmax, accel, decel, dt)
            elif mode == OperationMode.PROFILE_VELOCITY:
                target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
                target_v = max(-vlimit, min(vlimit, target_v))
                self._ramp_velocity(target_v, accel, decel, dt)
            elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION) \
                    and self.pp_target is not None:
                target = self.pp_target
                if target != self._csp_last:  # a new cyclic set-point: reached over one SYNC cycle
                    fresh = self._csp_last is not None and now - self._csp_t <= CYCLIC_GAP_S
                    self._csp_from = self.sp_pos if fresh else target
                    self._csp_period = self._sync_period_s
                    self._csp_last, self._csp_t = target, now
                # linear interpolation from the last set-point to this one over the cycle, as
                # drives do (0x60C2): no jump per cycle, no velocity left over when it ends
                done = (now - self._csp_t) / self._csp_period
                if done >= 1.0:
                    self.sp_pos, self.sp_vel = target, 0.0
                else:
                    self.sp_vel = (target - self._csp_from) / self._csp_period
                    self.sp_pos = self._csp_from + (target - self._csp_from) * done
                self.sp_acc = 0.0
            elif mode == OperationMode.CYCLIC_SYNC_VELOCITY:
                target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
                if store.has(OD.VELOCITY_OFFSET):
                    target_v += self._v(OD.VELOCITY_OFFSET, 0, 0)
                self.sp_vel, self.sp_acc = max(-vlimit, min(vlimit, target_v)), 0.0
            elif mode == OperationMode.HOMING and self.homing_active:
                speed = self._v(OD.HOMING_SPEEDS, 1, 1000) or 1000.0
                raw_index = p.index_position_counts
                raw_now = self.sp_pos - self.position_offset
                direction = 1.0 if raw_index > raw_now else -1.0
                self._ramp_velocity(direction * speed, accel, decel, dt)
                if (raw_index - (self.sp_pos - self.position_offset)) * direction <= 0:
                    self.theta = raw_index * k
                    self._home_here()
                elif abs(self.sp_pos - self._homing_start) > 20 * self.units_per_motor_rev:
                    self.homing_active = False
                    self.homing_error = True
            elif mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE):
                # no set-point of its own: it follows the shaft, so a stop (quick stop, halt, a
                # mode change) starts from where the joint is and how fast it turns
                self.sp_pos, self.sp_vel, self.sp_acc = self.position_counts, self.omega / k, 0.0
            else:
                self.sp_vel = self.sp_acc = 0.0
            # controller + plant, in motor radians, in sub-steps of at most PHYSICS_STEP_S so the
            # servo loops stay stable however late the simulator thread gets to run
            torque_mode = mode in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE) \
                and self.state == State.OPERATION_ENABLED
            position_loop = mode not in (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY) \
                or self.state != State.OPERATION_ENABLED or halt
            limit = float(store.get(OD.MAX_TORQUE, 0, 3000)) / 1000.0 * rated  # type: ignore[arg-type]
            self._servo(dt, k, limit, self._target_torque(rated) if torque_mode else None, position_loop)
            if not position_loop:  # velocity modes: no position loop, the set-point follows the shaft
                self.sp_pos = self.position_counts
            out += self._check_following(now, mode)
        else:
            self.omega = 0.0  # holding brake
            self.torque_nm = 0.0
            self._vel_integral = 0.0
            self.sp_pos = self.position_counts
            self.sp_vel = self.sp_acc = 0.0
        store.values[(OD.POSITION_ACTUAL, 0)] = self._as_type(OD.POSITION_ACTUAL, self.position_counts)
        store.values[(OD.VELOCITY_ACTUAL, 0)] = self._as_type(OD.VELOCITY_ACTUAL, self.omega / k / self._vconv)
        if store.has(OD.TORQUE_ACTUAL):
            store.values[(OD.TORQUE_ACTUAL, 0)] = self._as_type(OD.TORQUE_ACTUAL,
                                                                self.torque_nm / rated * 1000.0)
        if store.has(OD.FOLLOWING_ERROR_ACTUAL):
            store.values[(OD.FOLLOWING_ERROR_ACTUAL, 0)] = self._as_type(
                OD.FOLLOWING_ERROR_ACTUAL, self.sp_pos - self.position_counts)
        return out

    def _target_torque(self, rated: float) -> float:
        """PT / CST: 0x6071 (+ the torque offset 0x60B2 where the drive has it), in Nm."""
        permille = float(self.store.get(OD.TARGET_TORQUE, 0, 0))  # type: ignore[arg-type]
        if self.mode == OperationMode.CYCLIC_SYNC_TORQUE and self.store.has(OD.TORQUE_OFFSET):
            permille += float(self.store.get(OD.TORQUE_OFFSET, 0, 0))  # type: ignore[arg-type]
        return permille / 1000.0 * rated

    def _servo(self, dt: float, k: float, limit: float, target_tau: float | None, position_loop: bool) -> None:
        """Position loop (P) -> velocity loop (PI) -> current loop (first-order lag) -> motor
        and load (inertia, viscous and Coulomb friction, external load), in motor radians."""
        p = self.params
        kp, kv, ki = self._gains
        inertia = p.inertia_kg_m2
        steps = max(1, math.ceil(dt / PHYSICS_STEP_S))
        h = dt / steps
        alpha = h / (p.torque_lag_s + h)  # the current loop's lag, backward Euler (stable for any h)
        # the profile's set-point moves on within the tick with its acceleration (the set-point
        # velocity ramps, the feed-forward with it): a tick that comes late, 10-20 ms on a busy
        # machine, gives the same torque as ten on time, not a velocity step and then friction
        acc = self.sp_acc * k
        v_end = self.sp_vel * k
        v0 = v_end - acc * dt
        sp_rad = self.sp_pos * k - 0.5 * (v0 + v_end) * dt  # the profile's position at the start of the tick
        i_max = limit / ki if ki > 0 else 0.0
        stalled = self.faults.stalled
        omega, theta, tau, integral = self.omega, self.theta, self.torque_nm, self._vel_integral
        offset_rad = self.position_offset * k
        for i in range(steps):
            if target_tau is not None:
                tau_cmd = target_tau
            else:  # the set-point moves on within the tick as the shaft does: both at the sub-step's start
                t = h * i
                v_cmd = p.velocity_ff * (v0 + acc * t) + (
                    kp * (sp_rad + v0 * t + 0.5 * acc * t * t - theta - offset_rad) if position_loop else 0.0)
                err = v_cmd - omega
                integral = max(-i_max, min(i_max, integral + err * h))  # anti-windup
                tau_cmd = kv * err + ki * integral
            tau_cmd = max(-limit, min(limit, tau_cmd))
            tau += alpha * (tau_cmd - tau)
            if stalled:
                omega = 0.0
                continue
            drive = tau - p.load_nm - p.viscous_nm_s_rad * omega
            if omega == 0.0 and abs(drive) <= p.coulomb_nm:
                continue  # static friction holds the shaft
            friction = math.copysign(p.coulomb_nm, omega if omega != 0.0 else drive)
            new_omega = omega + h * (drive - friction) / inertia
            if omega != 0.0 and new_omega * omega < 0.0 and abs(drive) <= p.coulomb_nm:
                new_omega = 0.0  # friction stops the shaft; it does not reverse it
            theta += h * 0.5 * (omega + new_omega)
            omega = new_omega
        self.omega, self.theta, self.torque_nm, self._vel_integral = omega, theta, tau, integral

    def _check_position_limits(self, now: float) -> list[can.Message]:
        """0x607D while enabled: moving on beyond a software position limit is a fault."""
        if self.state != State.OPERATION_ENABLED or not self.store.has(OD.SOFTWARE_POSITION_LIMIT, 2):
            return []
        low = float(self.store.get(OD.SOFTWARE_POSITION_LIMIT, 1))  # type: ignore[arg-type]
        high = float(self.store.get(OD.SOFTWARE_POSITION_LIMIT, 2))  # type: ignore[arg-type]
        if low >= high:  # CiA 402: limits switched off
            return []
        pos = self.position_counts
        tolerance = LIMIT_TOLERANCE_REV * self.units_per_motor_rev
        if (pos > high + tolerance and self.omega > 0) or (pos < low - tolerance and self.omega < 0):
            logger.warning("node %d: position %.0f beyond the software limit [%.0f, %.0f]", self.node_id, pos, low, high)
            return self._raise_fault(EMCY_POSITION_LIMIT, now)
        return []

    def _as_type(self, index: int, value: float) -> int | float:
        var = self.store.vars[(index, 0)]
        if var.data_type in (0x08, 0x11):
            return value
        bits = var.size_bits or 32
        low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
        return max(low, min(high, int(round(value))))

    def _check_following(self, now: float, mode: int) -> list[can.Message]:
        if mode not in (OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_POSITION,
                        OperationMode.INTERPOLATED_POSITION) or self.state != State.OPERATION_ENABLED:
            self.following_since = None
            return []
        window = int(self.store.get(OD.FOLLOWING_ERROR_WINDOW, 0, 0))  # type: ignore[arg-type]
        if window <= 0 or window == 0xFFFFFFFF:
            return []
        if abs(self.sp_pos - self.position_counts) <= window:
            self.following_since = None
            return []
        if self.following_since is None:
            self.following_since = now
        timeout = int(self.store.get(OD.FOLLOWING_ERROR_TIMEOUT, 0, 0)) / 1000.0  # type: ignore[arg-type]
        if now - self.following_since >= timeout:
            self.following_since = None
            return self._raise_fault(0x8611, now)
        return []

    def _ramp_velocity(self, target: float, accel: float, decel: float, dt: float) -> None:
        dv = target - self.sp_vel
        rate = accel if abs(target) > abs(self.sp_vel) and target * self.sp_vel >= 0 else decel
        step = rate * dt
        self.sp_acc = math.copysign(rate, dv) if abs(dv) > step else dv / dt if dt else 0.0
        v_start = self.sp_vel
        self.sp_vel = target if abs(dv) <= step else self.sp_vel + math.copysign(step, dv)
        self.sp_pos += 0.5 * (v_start + self.sp_vel) * dt  # exact for the constant acceleration

    def _track_position(self, target: float, vmax: float, accel: float, decel: float, dt: float) -> None:
        """Online trapezoidal profile toward ``target`` (counts)."""
        dist = target - self.sp_pos
        v = self.sp_vel
        if abs(dist) < 0.5 and abs(v) < decel * dt:
            self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, 0.0
            return
        direction = math.copysign(1.0, dist)
        stop_dist = v * v / (2 * decel)
        if v * direction > 0 and stop_dist >= abs(dist):
            # braking: the constant deceleration that stops exactly on the target (a step late,
            # it is a little more than the profile's), so the set-point ends without a jump
            need = v * v / (2 * abs(dist))
            if abs(v) <= need * dt:
                self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, -v / dt
                return
            self.sp_acc = -direction * need
            self.sp_pos += v * dt + 0.5 * self.sp_acc * dt * dt
            self.sp_vel = v + self.sp_acc * dt
            return
        desired = direction * vmax
        # never ask for more speed than allows stopping on target
        cap = math.sqrt(2 * decel * abs(dist))
        desired = max(-cap, min(cap, desired))
        self._ramp_velocity(desired, accel, decel, dt)
        if (target - self.sp_pos) * direction < 0:  # passed it within this step
            self.sp_pos, self.sp_vel, self.sp_acc = target, 0.0, 0.0

    def _update_status(self) -> None:
        sw = STATUS_BITS[self.state] | SW_REMOTE
        if not self.faults.sto_low and self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                                                      *POWERED):
            sw |= SW_VOLTAGE_ENABLED
        mode = self.mode
        if self.state == State.OPERATION_ENABLED:
            if mode == OperationMode.PROFILE_POSITION:
                if self.pp_target is None or (abs(self.sp_pos - self.pp_target) < 0.5 and self.sp_vel == 0.0
                                              and abs(self.position_counts - self.pp_target) <= self._window()):
                    sw |= SW_TARGET_REACHED
                cw = int(self.store.get(OD.CONTROLWORD, 0))  # type: ignore[arg-type]
                if cw & CW_NEW_SETPOINT and self._setpoint_ack:
                    if self._now >= self._ack_at:  # a slow drive acknowledges later (fault injection)
                        sw |= SW_OMS12
                else:
                    self._setpoint_ack = False
            elif mode == OperationMode.PROFILE_VELOCITY:
                target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
                if abs(self.omega / self._rad_per_count - target_v) < max(10.0, abs(target_v) * 0.02):
                    sw |= SW_TARGET_REACHED
                if abs(self.omega / self._rad_per_count) < 10.0:
                    sw |= SW_OMS12
            elif mode == OperationMode.HOMING:
                if self.homing_done:
                    sw |= SW_OMS12 | SW_TARGET_REACHED
                if self.homing_error:
                    sw |= SW_OMS13
            elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.CYCLIC_SYNC_VELOCITY,
                          OperationMode.CYCLIC_SYNC_TORQUE):
                sw |= SW_OMS12  # the drive follows the cyclic target
            elif mode == OperationMode.INTERPOLATED_POSITION:
                if self._ip_enabled:
                    sw |= SW_OMS12  # ip mode active
                if self.pp_target is None or abs(self.pp_target - self.position_counts) <= self._window():
                    sw |= SW_TARGET_REACHED
            else:
                sw |= SW_TARGET_REACHED
        if self.following_since is not None:
            sw |= SW_WARNING
        self.store.values[(OD.STATUSWORD, 0)] = sw

    def _window(self) -> float:
        return max(2.0, self.units_per_motor_rev / 3600.0)

    @property
    def statusword(self) -> int:
        return int(self.store.get(OD.STATUSWORD, 0))  # type: ignore[arg-type]

    def _msg(self, cob_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=0.0)

    def status_line(self) -> str:
        return (f"node {self.node_id:3d} {self.name:<10} NMT={self.nmt.name:<15} {self.state.name:<22}"
                f" mode={self.mode:<2} pos={self.position_counts:12.0f} vel={self.omega / self._rad_per_count:9.0f}"
                f" torque={self.torque_nm:+.3f}Nm err=0x{self.error_code:04X}")


"""Layer 0 of the simulated drive: every attribute it has, declared in one place, its units
(from its factor group and SI velocity unit) and small helpers.

Owner of all of a :class:`SimulatedDrive`'s state: its runner thread (the drive is not
thread-safe; :class:`~virtual_can.sim.runner.DriveSimulator` calls it from one thread).
"""

from __future__ import annotations

import collections
import logging
import math
import random

import can
from canopen.objectdictionary import ObjectDictionary

from can_config.objects import OD, NmtState
from virtual_can.sim.drive.model import Faults, MotorParams, Pdo, State
from virtual_can.sim.objects import ObjectStore
from virtual_can.sim.sdo import SdoServer

logger = logging.getLogger(__name__)


class DriveBase:
    """Layer 0 of :class:`SimulatedDrive`: every attribute, declared here; units; helpers."""

    def __init__(self, node_id: int, od: ObjectDictionary, params: MotorParams | None = None,
                 *, name: str | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node_id={node_id}: CANopen node ids are 1..127")
        self.node_id = node_id
        self.name = name or f"drive{node_id}"
        self.params = params or MotorParams()
        self._gains = self.params.gains()
        self.store = ObjectStore(od)
        self.sdo = SdoServer(self.store)
        self.faults = Faults()
        self._rng = random.Random(node_id)  # the random part of a late SYNC answer (reproducible)
        self._now = 0.0
        self._plant_at = 0.0  # the runner's time the plant's state (theta, omega) is of: the last tick's
        #: the least (handling time - bus stamp) of a SYNC seen: a SYNC's bus stamp on the runner's clock
        self._bus_offset: float | None = None
        #: every profile-position target the drive accepted, in order (None: not recorded)
        self.accepted_targets: list[float] | None = None
        #: the set-point speed (counts/s) each time a controlword switched its power stage off while it
        #: still moved (mid-ramp): a real drive's shaft coasts from there, this one's brake holds it
        self.cut_at_speed: list[float] = []
        self.nmt = NmtState.BOOTUP
        self.counters = {"tpdo": 0, "rpdo": 0, "emcy": 0, "sdo": 0}
        # the drive's units (_units_from_od)
        self.units_per_motor_rev = 4096.0
        self._rad_per_count = 2 * math.pi / 4096
        self._vconv = 1.0  # position units/s per velocity unit
        self.theta = 0.0  # the shaft's angle, motor radians (a reset does not move it)
        self.position_offset = 0.0  # set by homing; kept over a reset
        self._init_motion()
        self._init_comm()

    def _init_motion(self) -> None:
        """The CiA 402 state machine, the set-point generator and the plant's motion, as after a
        reset (the shaft's angle and the homing offset stay)."""
        self.state = State.SWITCH_ON_DISABLED
        self.prev_cw = 0
        self.omega = 0.0
        self.torque_nm = 0.0
        self._vel_integral = 0.0
        self.sp_pos = self.theta / self._rad_per_count
        self.sp_vel = 0.0
        self.sp_acc = 0.0
        self.pp_target: float | None = None
        self.homing_active = False
        self.homing_done = False
        self.homing_error = False
        self._homing_start = 0.0
        self.following_since: float | None = None
        self._csp_last: float | None = None
        self._csp_t = 0.0
        self._csp_from = 0.0  # the cyclic set-point being left, and the cycle it is left over
        self._csp_period = 1e-3
        self._syncs = 0  # SYNCs heard
        self._csp_written = 0  # the SYNC count when the newest cyclic set-point was written
        self._csp_sync = 0  # ... and when the one being followed was, last
        self._csp_left: float | None = None  # the set-point the last cyclic step left
        self._last_sync = -1.0
        self._sync_period_s = 0.01  # measured from the SYNCs (a drive's 0x1006 / 0x60C2)
        self.error_code = 0
        self._setpoint_ack = False
        self._ack_at = 0.0  # the acknowledge shows from then on (fault injection: a slow drive)
        self._slow_transition: tuple[State, float] | None = None  # (state, when) of a slow enabling step
        self._pending_emcy_reset = False

    def _init_comm(self) -> None:
        """NMT, SDO, PDO, heartbeat consumer and node guarding state (reset by _reset_comm)."""
        self.rpdos: dict[int, Pdo] = {}
        self.tpdos: list[Pdo] = []
        self._pending_rpdos: list[tuple[Pdo, bytes]] = []
        self._cycle_rpdos: list[tuple[Pdo, bytes]] = []  # faults.cw_per_cycle: read at the tick
        self._delayed_sdo: tuple[float, bytes] | None = None
        #: frames that leave later, (when on the runner's clock, frame), in order (Faults.sync_delay_s)
        self._held: collections.deque[tuple[float, can.Message]] = collections.deque()
        self._consumers: dict[int, tuple[int, float]] = {}  # 0x1016 sub -> (watched node, consumer time s)
        self._consumer_seen: dict[int, float] = {}  # 0x1016 sub -> bus time its producer was last heard
        self._guard_toggle = 0  # node guarding: the toggle bit of the next answer (0 after a reset)
        self._guarded_at: float | None = None  # the last guard's bus time; life guarding armed by the first
        self._next_heartbeat = 0.0

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

    @property
    def mode(self) -> int:
        return int(self.store.get(OD.MODES_OF_OPERATION_DISPLAY, 0))  # type: ignore[arg-type]

    @property
    def quick_stop_option(self) -> int:
        """What its quick stop does: 0x605A (2 where the drive has none: the common default), unless
        its firmware fixes it (the ``quick_stop_option`` fault)."""
        fixed = self.faults.quick_stop_option
        return fixed if fixed is not None else int(self.store.get(OD.QUICK_STOP_OPTION, 0, 2))  # type: ignore[arg-type]

    @property
    def position_counts(self) -> float:
        return self.theta / self._rad_per_count + self.position_offset

    @property
    def statusword(self) -> int:
        return int(self.store.get(OD.STATUSWORD, 0))  # type: ignore[arg-type]

    def _as_type(self, index: int, value: float) -> int | float:
        var = self.store.vars[(index, 0)]
        if var.data_type in (0x08, 0x11):
            return value
        bits = var.size_bits or 32
        low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
        return max(low, min(high, int(round(value))))

    def _window(self) -> float:
        return max(2.0, self.units_per_motor_rev / 3600.0)

    def _msg(self, cob_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=0.0)

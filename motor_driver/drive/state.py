"""The state cache: what the driver knows of one drive, fed by the bus's receive thread.

Owner: the bus's receive thread (``_on_tpdo``, ``_on_heartbeat``, ``_on_emcy``), the only
writer of the received state (statusword, position, velocity, torque, mode display, NMT
state, last EMCY, their times), each field replaced in one assignment. It notifies
``_status_event`` waiters and sends one thing only, the set-point handshake's reply
(:mod:`motor_driver.setpoint`, which owns its own state under its own short lock). It takes
no lock a command or a wait holds. Boot (the bus's worker, while the drive is not booted)
seeds the statusword, position and mode it read by SDO. Nothing else writes these fields.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from can_config.errors import BusLostError, MotorError
from can_config.objects import OD, FunctionCode, NmtState, emcy_text
from motor_driver.cia402 import FAULT_STATES, SW, Command, State, decode_state
from motor_driver.drive.constants import JUMP_CONFIRMATIONS, MAX_ACCEL_GAP_S, TRANSITION_TIMEOUT_S
from motor_driver.pdo import PdoPlan, TpdoLayout, plan_pdos
from motor_driver.setpoint import SetpointHandshake
from motor_driver.units import Scale

logger = logging.getLogger(__name__)


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


class DriveCache:
    """Layer 0 of :class:`motor_driver.drive.Drive`: identity, the PDO plan, and the received state."""

    # written by layers above (motor_driver.drive.frames), read here by the receive thread
    _cw: int
    _enable_sent_at: float
    _handshake: SetpointHandshake

    def __init__(self, config: DriveConfig, network: canopen.Network, od: ObjectDictionary, *,
                 host_node_id: int = 127, sync_period_s: float = 0.01) -> None:
        self.config = config
        self.host_node_id = host_node_id
        self.name = config.name
        self.node_id = config.node_id
        self.network = network
        self.od = od
        self.node = canopen.RemoteNode(config.node_id, od)
        self.node.sdo.RESPONSE_TIMEOUT = config.sdo_timeout_s
        network.add_node(self.node)
        # the driver decodes EMCY itself (_on_emcy); canopen's consumer would keep every EMCY in
        # a list that is never trimmed, for as long as the process runs
        network.unsubscribe(FunctionCode.EMCY + config.node_id, self.node.emcy.on_emcy)
        self.scale = Scale(config.counts_per_deg, config.rated_torque_nm, config.gear_ratio,
                           invert=config.invert, offset_deg=config.offset_deg)
        self.plan: PdoPlan = plan_pdos(od, config.node_id)
        for index in self.plan.sdo_only:
            logger.warning("node %d: 0x%04X cannot be PDO-mapped on this drive; using SDO for it", config.node_id, index)
        self.sync_period_s = sync_period_s
        self._init_received()
        self._init_lifecycle()
        self._max_counts_s = int(abs(self.scale.counts_per_deg * config.max_velocity_deg_s)) or 1
        self._jump_margin_counts = max(4.0, self.scale.counts_per_deg)  # one degree
        self._has_torque = any(OD.TORQUE_ACTUAL in p.indexes for p in self.plan.tpdos)
        self._layouts = {p.cob_id: TpdoLayout.from_map(p) for p in self.plan.tpdos}
        self._init_state()

    def _init_state(self) -> None:
        """Each layer's own state, set up once identity, scale and PDO plan are: a layer extends
        it (``super()._init_state()`` first). Nothing is subscribed yet (:class:`Drive` does that)."""

    def _init_received(self) -> None:
        """The state from PDOs, heartbeat and EMCY (the receive thread's)."""
        self.statusword = 0
        #: a FAULT statusword was seen since the last enable() / recover() / boot: set by the
        #: receive thread, cleared by those operations; motion is refused while it is set, so a
        #: drive whose statusword flickers through FAULT is never commanded between two samples
        self.fault_seen: int | None = None
        self.mode_display = 0
        self.position_counts = 0
        self.velocity_counts_s = 0
        #: the slope of the last two velocity samples, counts/s^2: how a torque-commanded joint
        #: speeds up while the limit guard reacts (receive thread; 0 after a gap in the samples)
        self.accel_counts_s2 = 0.0
        self._accel_from = (0, 0.0)  # (velocity, sample time) the slope is taken from (receive thread)
        self.torque_permille: float = math.nan
        self.stamp = 0.0
        self.nmt_state = "UNKNOWN"
        self._reported_nmt = "UNKNOWN"  # the last state the drive's own heartbeat said (receive thread)
        self._bootup_at = 0.0  # when it last sent a boot-up (receive thread)
        self._operational_at = 0.0  # its last heartbeat saying OPERATIONAL (receive thread)
        self.last_heartbeat = 0.0
        self.last_emcy: Emcy | None = None
        self._status_event = threading.Condition()
        self.tpdo_count = 0
        self._position_seq = 0
        self._position_t = 0.0
        self._suspect_position: tuple[int, int] | None = None  # (value, samples agreeing since)
        self.implausible_samples = 0
        self.rx_monotonic = 0.0  # when the last TPDO arrived (receive thread)
        self._sw_enabled = False  # the last statusword said Operation Enabled (receive thread)
        self.behind_back: tuple[float, str] = (0.0, "")  # (when, what) changed without this driver
        # node guarding (CiA 301), for a drive without a heartbeat consumer: the supervisor sends
        # the guard (HostWatch.guard, its thread only); the receive thread checks each answer's toggle
        self.guarding = False  # written by boot (the bus's worker) while the drive is not booted
        self._guard_toggle = 0  # the toggle bit the next answer must carry (receive thread)
        self.guard_errors = 0  # answers with a wrong toggle bit (receive thread)

    def _init_lifecycle(self) -> None:
        """Booted, lost, closed: written by boot (the bus's worker), the supervisor and the
        receive thread (a boot-up), each a single assignment read without a lock."""
        self.lost = False
        self.booted = False
        self.closed = False  # set by MotorDriver.close: no command is accepted after it
        self.rebooted = threading.Event()
        self._bootup = threading.Event()
        self.boot_count = 0
        #: set by the supervisor while another master is on the bus: why commands are refused
        self.foreign_master = ""
        self.velocity_commanded = False  # a velocity or torque command is live (the watchdog's)
        self.last_velocity_cmd = 0.0
        self.was_enabled = False
        #: how the drive watches the host (boot writes it; enable reads it), or None: nothing stops it if the host dies
        self.host_watch: str | None = None
        self.host_watch_problem: str | None = None  # why there is no host watch (after boot)

    def seed(self, statusword: int, position_counts: int) -> None:
        """Boot (the bus's worker, drive not booted, before NMT start: no PDO flows): the state it
        read by SDO, as the receive thread's cache starts from it. The next position TPDO is
        trusted as it comes (the position was just read)."""
        self.statusword = statusword
        self.position_counts = position_counts
        self._position_t = 0.0

    def subscribe(self) -> None:
        """Hand the drive's COB-IDs to the receive thread: called once every layer is set up."""
        for cob in self._layouts:
            self.network.subscribe(cob, self._on_tpdo)
        self.network.subscribe(FunctionCode.HEARTBEAT + self.node_id, self._on_heartbeat)
        self.network.subscribe(FunctionCode.EMCY + self.node_id, self._on_emcy)

    def _on_tpdo(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        layout = self._layouts[cob_id]
        try:
            values = layout.codec.unpack_from(data)
        except struct.error:
            logger.warning("node %d: TPDO 0x%03X with %d bytes, expected %d; ignored",
                           self.node_id, cob_id, len(data), layout.codec.size)
            return
        for index, value in zip(layout.indexes, values, strict=True):
            if index == OD.STATUSWORD:
                if decode_state(value) in FAULT_STATES:
                    self.fault_seen = value
                self.statusword = value
            elif index == OD.POSITION_ACTUAL:
                if not self._plausible_position(value, timestamp):
                    continue
                self.position_counts = value
                self._position_seq += 1
            elif index == OD.VELOCITY_ACTUAL:
                self._track_accel(value, timestamp)
                self.velocity_counts_s = value
            elif index == OD.TORQUE_ACTUAL:
                self.torque_permille = value
            elif index == OD.MODES_OF_OPERATION_DISPLAY:
                self.mode_display = value
        self.stamp = timestamp
        self.rx_monotonic = time.monotonic()
        self.tpdo_count += 1
        if OD.STATUSWORD in layout.indexes:
            enable = int(Command.ENABLE_OPERATION)
            now_enabled = decode_state(self.statusword) == State.OPERATION_ENABLED
            ours = self.rx_monotonic - self._enable_sent_at < TRANSITION_TIMEOUT_S  # a stop may have followed it
            if now_enabled and not self._sw_enabled and self.booted and self._cw & enable != enable and not ours:
                self.behind_back = (self.rx_monotonic, f"node {self.node_id} became OPERATION_ENABLED, which this"
                                                       " driver did not command")
            self._sw_enabled = now_enabled
            if not self._handshake.idle:
                try:  # the one reply the receive thread sends
                    self._handshake.on_status(bool(self.statusword & SW.SETPOINT_ACK))
                except MotorError as err:  # never let a send failure kill the receive thread
                    logger.warning("node %d: setpoint handshake: %s", self.node_id, err)
            with self._status_event:
                self._status_event.notify_all()

    def _track_accel(self, velocity_counts_s: int, timestamp: float) -> None:
        """Receive thread: the slope from the last sample at least half a SYNC period older (two
        frames that queued up and arrive together give no slope of their own)."""
        before, t_before = self._accel_from
        gap = timestamp - t_before
        if 0.0 <= gap < 0.5 * self.sync_period_s:
            return
        self.accel_counts_s2 = (velocity_counts_s - before) / gap if 0.0 < gap <= MAX_ACCEL_GAP_S else 0.0
        self._accel_from = (velocity_counts_s, timestamp)

    def _plausible_position(self, value: int, timestamp: float) -> bool:
        """Reject a position the joint cannot have reached since the last one (a corrupted or
        foreign frame), unless JUMP_CONFIRMATIONS further samples agree with it (homing, a
        reboot, a real jump)."""
        last_t = self._position_t
        self._position_t = timestamp
        if not last_t:
            return True
        limit = self._max_counts_s * 2.0 * max(timestamp - last_t, 0.001) + self._jump_margin_counts
        if abs(value - self.position_counts) <= limit:
            self._suspect_position = None
            return True
        suspect = self._suspect_position
        if suspect is not None and abs(value - suspect[0]) <= limit:
            if suspect[1] + 1 >= JUMP_CONFIRMATIONS:
                self._suspect_position = None
                return True  # confirmed
            self._suspect_position = (value, suspect[1] + 1)
            return False
        self._suspect_position = (value, 0)
        self.implausible_samples += 1
        logger.debug("node %d: position %d implausible after %d; held for confirmation", self.node_id, value,
                     self.position_counts)
        return False

    def _on_heartbeat(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        state = data[0] & 0x7F
        if self.guarding and state != NmtState.BOOTUP:  # a guard's answer: its toggle must alternate
            toggle = data[0] >> 7
            if toggle != self._guard_toggle:
                self.guard_errors += 1
                logger.warning("node %d (%s): node guarding answer with toggle %d, expected %d; not counted",
                               self.node_id, self.name, toggle, self._guard_toggle)
                self._guard_toggle = toggle ^ 1  # in step again from the next answer on
                return
            self._guard_toggle ^= 1
        self.last_heartbeat = time.monotonic()
        if state == NmtState.BOOTUP:
            self.nmt_state = self._reported_nmt = "BOOTUP"
            self._bootup_at = self.last_heartbeat
            self._bootup.set()
            if self.booted:
                logger.warning("node %d (%s) sent boot-up: it power-cycled or reset; it will be"
                               " configured again", self.node_id, self.name)
                self.booted = False
                self.rebooted.set()
            return
        # compared with what the drive itself said last, never with what boot() assumed after its
        # NMT start: a heartbeat sent just before the drive obeyed it is still on its way then
        was = self._reported_nmt
        try:
            self.nmt_state = NmtState(state).name
        except ValueError:
            self.nmt_state = f"0x{state:02X}"
        self._reported_nmt = self.nmt_state
        if state == NmtState.OPERATIONAL:
            self._operational_at = self.last_heartbeat
        if self.booted and state != NmtState.OPERATIONAL and was == "OPERATIONAL":  # the change, not the state
            self.behind_back = (self.last_heartbeat, f"node {self.node_id} went {self.nmt_state} without an NMT"
                                                     " command from this driver")
        # a heartbeat brings back only a drive whose heartbeat was late (still booted); one the
        # supervisor marked lost with its bus is back when boot() configured it again. A heartbeat
        # still queued in the receive thread when the bus went must not undo that mark: nothing
        # would declare the drive lost again (check_heartbeat watches booted drives only).
        if self.lost and self.booted:
            logger.warning("node %d (%s): heartbeat back", self.node_id, self.name)
            self.lost = False

    def _on_emcy(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 3:
            return
        code, register = struct.unpack_from("<HB", data)
        self.last_emcy = Emcy(code, register, emcy_text(code), timestamp)
        if code:
            logger.error("node %d (%s): EMCY 0x%04X %s (error register 0x%02X)", self.node_id,
                         self.name, code, emcy_text(code), register)
        else:
            logger.info("node %d (%s): EMCY error reset", self.node_id, self.name)

    @property
    def state(self) -> State:
        return decode_state(self.statusword)

    @property
    def angle_deg(self) -> float:
        return self.scale.counts_to_deg(self.position_counts)

    def snapshot(self) -> DriveState:
        sw = self.statusword
        state = decode_state(sw)
        emcy = self.last_emcy
        error_code = emcy.code if emcy is not None and state in FAULT_STATES else 0
        if emcy is not None and not error_code and emcy.code:
            error_code = emcy.code
        now = time.monotonic()
        hb_age = now - self.last_heartbeat if self.last_heartbeat else math.inf
        data_age = now - self.rx_monotonic if self.rx_monotonic else math.inf
        stale = data_age > self.config.stale_after_syncs * self.sync_period_s
        torque = self.scale.permille_to_nm(self.torque_permille) if self._has_torque else math.nan
        return DriveState(
            name=self.name, node_id=self.node_id, angle_deg=self.angle_deg,
            velocity_deg_s=self.scale.counts_s_to_deg_s(self.velocity_counts_s), torque_nm=torque,
            statusword=sw, state=state, mode=self.mode_display, nmt=self.nmt_state,
            enabled=state == State.OPERATION_ENABLED and not self.lost and not stale,
            fault=state in FAULT_STATES or self.lost,
            lost=self.lost, error_code=error_code,
            error_text=emcy_text(error_code) if error_code else "",
            stamp=self.stamp, heartbeat_age_s=hb_age,
            target_reached=bool(sw & SW.TARGET_REACHED), data_age_s=data_age, stale=stale,
            foreign_master=self.foreign_master)

    def _send(self, cob_id: int, data: bytes) -> None:
        """One frame out; a dead bus becomes BusLostError (the supervisor reconnects)."""
        try:
            self.network.send_message(cob_id, data)
        except (can.CanError, OSError, RuntimeError) as err:
            raise BusLostError(f"{self.name} (node {self.node_id}): cannot send 0x{cob_id:03X}: the bus is"
                               f" gone ({err}); nothing moves until it is back and the drive is enabled again") from err

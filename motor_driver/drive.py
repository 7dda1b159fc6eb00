"""One CiA 402 drive on a CANopen network: boot, state machine, commands, PDO state.

Hot path: TPDO callbacks (canopen's notifier thread) unpack with one precompiled struct and
store plain attributes; commands build their payload with a pure function and send one
frame. Every failure raises a typed error from :mod:`can_config.errors`; nothing is logged
and swallowed.

Threads and what each owns:

- the bus's receive thread (``_on_tpdo``, ``_on_heartbeat``, ``_on_emcy``): the received
  state (statusword, position, velocity, torque, mode display, NMT state, last EMCY, their
  times), each field replaced in one assignment; it notifies ``_status_event`` waiters and
  sends one thing only, the set-point handshake's reply (:mod:`motor_driver.setpoint`, which
  owns its own state under its own short lock). It takes no lock a command or a wait holds.
- command threads (the API, ROS callbacks): ``_cw``, ``_target_counts``, the velocity
  watchdog's timestamps, under ``_lock``, which is held only to decide and send a frame or
  two (at most ``COMMAND_LOCK_WAIT_S`` waited for it) and never while waiting for the drive.
  Operations that wait (enable, homing, recover, the stops) mark the drive busy instead
  (``_operation``): commands meanwhile are refused at once; a stop preempts them.
- the driver's supervisor: changes a drive only through its methods (``check_heartbeat``,
  ``mark_lost``, ``set_foreign_master``, ``stop_velocity``, ``guard_limits``), none of which
  waits; the bus's worker runs ``reconfigure`` (boot after a reset), which may take seconds,
  and ``quick_stop_by_sdo`` (the SDO copy of the quick stop on losing control, where needed).
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import GENERIC_EDS, ON_HOST_LOSS, DriveConfig, SdoSetting
from can_config.eds import consumer_subs, has_object, variable
from can_config.errors import (
    BootError,
    BusLostError,
    CommandRejected,
    DriveStateError,
    DriveTimeoutError,
    MotorError,
    SdoError,
    SdoTimeoutError,
)
from can_config.objects import (
    CIA402_PROFILE,
    OD,
    STRUCT_FORMAT,
    SUPPORTED_MODE_BIT,
    NmtCommand,
    NmtState,
    OperationMode,
    emcy_text,
    sdo_abort_text,
)
from motor_driver.cia402 import (
    CW,
    FAULT_STATES,
    SW,
    Command,
    State,
    controlword,
    decode_state,
    next_step_to_enable,
)
from motor_driver.pdo import PdoPlan, TpdoLayout, encode_rpdo, mapping_writes, plan_pdos
from motor_driver.safety import SafetyCheck, guard_settings, judge
from motor_driver.setpoint import SetpointHandshake
from motor_driver.units import (
    Scale,
    check_counts,
    check_limits,
    nearest_equivalent,
    read_unit_objects,
    require_finite,
    scale_from_objects,
)

logger = logging.getLogger(__name__)


def host_consumer_entry(host_node_id: int, timeout_s: float) -> int:
    """A 0x1016 sub-entry: watch ``host_node_id``'s heartbeat with this consumer time (CiA 301)."""
    return (host_node_id & 0x7F) << 16 | max(1, min(0xFFFF, int(round(timeout_s * 1000))))

#: Objects no tool or service may write by SDO (see Drive.sdo_write_checked), each with why:
#: they move the motor, bypass a limit, or undo what stops the drive when the host is gone.
_TARGET = "it is a motion target; use move/jog (limits enforced)"
PROTECTED_OBJECTS: dict[int, str] = {
    OD.CONTROLWORD: "it drives the state machine (enable, quick stop); use enable/disable",
    OD.MODES_OF_OPERATION: "it changes the operation mode under the driver",
    OD.TARGET_POSITION: _TARGET, OD.TARGET_VELOCITY: _TARGET, OD.TARGET_TORQUE: _TARGET,
    OD.VELOCITY_OFFSET: _TARGET, OD.TORQUE_OFFSET: _TARGET,
    OD.SOFTWARE_POSITION_LIMIT: "it is the drive's position limit; set min_deg/max_deg in the config",
    OD.MAX_PROFILE_VELOCITY: "it is a velocity limit; set max_velocity_deg_s in the config",
    OD.MAX_TORQUE: "it is the torque limit; set max_torque_nm in the config",
    OD.PROFILE_VELOCITY: "it is the speed of every profile move, checked against max_velocity_deg_s; use move --speed",
    OD.PROFILE_ACCELERATION: "it is the ramp of every profile move; set profile_acceleration_deg_s2 in the config",
    OD.PROFILE_DECELERATION: "it is the ramp of every profile move; set profile_acceleration_deg_s2 in the config",
    OD.QUICK_STOP_DECELERATION: "the drive's quick stop (and its stop when the host is gone) brakes by it",
    OD.QUICK_STOP_OPTION: "it decides what the drive's quick stop does (the host-loss stop relies on it)",
    OD.ABORT_CONNECTION_OPTION: "it decides what the drive does when the host is gone (on_host_loss in the config)",
    OD.CONSUMER_HEARTBEAT_TIME: "it is how the drive watches the host's heartbeat (the stop when the host dies)",
    OD.HOMING_METHOD: "homing moves the motor by it; set homing in the config",
    OD.HOMING_SPEEDS: "homing moves the motor by it; set homing in the config",
    OD.PRODUCER_HEARTBEAT_TIME: "the driver watches the drive's heartbeat at the configured period; a change makes"
                                " it declare the drive lost, or miss a loss (heartbeat_ms in the config)",
    OD.COB_ID_SYNC: "it moves the SYNC every PDO of the drive runs on",
}


def protected_reason(index: int) -> str | None:
    """Why writing ``index`` by SDO is refused, or None when it may be written."""
    if 0x1400 <= index <= 0x1BFF:
        return "it changes the PDO set the driver configured (a PDO could then carry motion targets)"
    return PROTECTED_OBJECTS.get(index)


#: An SDO read of an object whose type has no size (a string, a domain) brings at most this much;
#: a drive that announces or sends more is cut off with an abort.
SDO_UPLOAD_MAX_BYTES = 1024
#: A whole SDO read (all its segments) takes at most this many SDO timeouts.
SDO_TRANSFER_TIMEOUTS = 4
SDO_ABORT_OUT_OF_MEMORY = 0x0504_0005
SDO_ABORT_TIMEOUT = 0x0504_0000
#: Timeouts (seconds); module constants so tests and benchmarks can override them.
TRANSITION_TIMEOUT_S = 1.0
MODE_SWITCH_TIMEOUT_S = 1.0
STATE_POLL_S = 0.002
REBOOT_RETRY_S = 0.5
#: How long a command waits for another command's frames before it is refused (never for an
#: operation such as enable or homing: that refuses at once).
COMMAND_LOCK_WAIT_S = 0.003
#: 0x605A: slow down on the quick-stop ramp, then Switch On Disabled.
QUICK_STOP_THEN_DISABLE = 2
#: Reaction time of the driver's own limit guard (supervisor period, SYNC, TPDO age), as distance
#: travelled at the current speed before braking starts.
LIMIT_MARGIN_S = 0.05
#: The limit guard moves a sampled position on by its velocity for at most this long.
MAX_EXTRAPOLATION_S = 0.2
#: How long a torque-commanded joint goes on speeding up once the guard has decided to brake:
#: the quick stop reaches the drive with the next SYNC, a supervisor period after the samples.
LIMIT_ACCEL_MARGIN_S = 0.025
#: Velocity samples further apart than this give no acceleration (a gap, not a slope).
MAX_ACCEL_GAP_S = 0.2
#: A position the joint cannot have reached is taken only once this many further samples agree
#: with it (a real jump: homing, a reboot). One corrupted TPDO is held back, and so is the same
#: corruption twice in a row (at the emulator's 10 % corruption rate, estimated at one two-second
#: run in a hundred; seen once: a wheel reported 47 million degrees for a SYNC period).
JUMP_CONFIRMATIONS = 2
NO_HOST_WATCH = "no drive-side stop on host loss"
#: SDO aborts of a value out of the object's range (CiA 301): the drive cannot take that entry.
VALUE_RANGE_ABORTS = frozenset({0x0609_0030, 0x0609_0031, 0x0609_0032, 0x0609_0036})
#: A continuous joint's degree command is an angle modulo 360; beyond this it is a mistake.
CONTINUOUS_COMMAND_LIMIT_DEG = 360.0
#: At boot, how long to listen for the drive's heartbeat before asking its error history.
HOST_LOSS_CHECK_WAIT_S = 0.25
#: EMCY / error history code of a drive whose heartbeat consumer lost the host (CiA 301).
EMCY_HOST_LOST = 0x8130
#: Modes whose command is a velocity (the watchdog and the limit guard send zero velocity) ...
#: The controlword bits of Enable Operation (switch on, enable voltage, no quick stop, enable
#: operation): motion frames go out only while this driver's last controlword had them all.
ENABLED_CW_MASK = 0x000F
VELOCITY_MODES = (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY)
#: ... and a torque (they send zero torque and, at a limit, quick-stop).
TORQUE_MODES = (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE)


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


class Drive:
    """One drive. Created by :class:`motor_driver.driver.MotorDriver`; methods are thread-safe."""

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
        network.unsubscribe(0x80 + config.node_id, self.node.emcy.on_emcy)
        self.scale = Scale(config.counts_per_deg, config.rated_torque_nm, config.gear_ratio,
                           invert=config.invert, offset_deg=config.offset_deg)
        self.plan: PdoPlan = plan_pdos(od, config.node_id)
        for index in self.plan.sdo_only:
            logger.warning("node %d: 0x%04X cannot be PDO-mapped on this drive; using SDO for it", config.node_id, index)
        self._lock = threading.RLock()  # serialises commands; never held while waiting for the drive
        self._busy: str | None = None  # the operation in progress (enable, home, a stop, ...)
        self._busy_owner: int | None = None  # its thread
        self._generation = 0  # counts operations: a preempted one notices
        self._preempted: tuple[int, str] = (0, "")  # operations older than this generation were stopped
        self._cw = 0  # last device-control controlword (no edge bits); written under _lock only
        self._enable_sent_at = 0.0  # when this driver last sent Enable Operation (under _lock)
        #: tests only: called at named points of the state machine to force an interleaving (_hook)
        self.interleave: Callable[[str], None] | None = None
        self._target_counts = 0
        self._handshake = SetpointHandshake(self._send_setpoint, self._clear_setpoint)
        # state from PDOs / heartbeat / EMCY (written by the notifier thread)
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
        self.lost = False
        self.booted = False
        self.closed = False  # set by MotorDriver.close: no command is accepted after it
        self._supported_modes: int | None = None  # 0x6502, read once per boot
        self.last_emcy: Emcy | None = None
        self.rebooted = threading.Event()
        self._bootup = threading.Event()
        self._status_event = threading.Condition()
        self.tpdo_count = 0
        self.watchdog_stops = 0
        self._position_seq = 0
        self._position_t = 0.0
        self._suspect_position: tuple[int, int] | None = None  # (value, samples agreeing since)
        self.implausible_samples = 0
        self.boot_count = 0
        self.sync_period_s = sync_period_s
        #: how the drive watches the host (set at boot), or None: nothing stops it if the host dies
        self.host_watch: str | None = None
        self.host_watch_problem: str | None = None  # why there is no host watch (after boot)
        #: set by the driver: the bus carries remote frames (a kernel bus; socketcand's rawmode cannot)
        self.remote_frames = False
        # node guarding (CiA 301), for a drive without a heartbeat consumer: the supervisor sends
        # the guard (guard(), its thread only); the receive thread checks each answer's toggle
        self.guarding = False  # written by boot (the bus's worker) while the drive is not booted
        self._guard_toggle = 0  # the toggle bit the next answer must carry (receive thread)
        self._next_guard = 0.0  # supervisor only
        self.guard_errors = 0  # answers with a wrong toggle bit (receive thread)
        self._guardable = False  # boot's: node guarding chosen and possible on this bus
        self.safety: tuple[SafetyCheck, ...] = ()  # read back after each boot (motor_driver.safety)
        self.limit_stops = 0
        self.rx_monotonic = 0.0  # when the last TPDO arrived (receive thread)
        self._sw_enabled = False  # the last statusword said Operation Enabled (receive thread)
        #: set by the supervisor while another master is on the bus: why commands are refused
        self.foreign_master = ""
        self.behind_back: tuple[float, str] = (0.0, "")  # (when, what) changed without this driver
        self.last_velocity_cmd = 0.0
        self.velocity_commanded = False
        self.host_loss_stops = 0  # boots that found the drive stopped by its host watch (boot thread)
        self._stream_velocity_counts_s = 0  # the last CSV target (command threads, under _lock)
        self.was_enabled = False
        self.turns_offset_deg = 0.0
        self._max_counts_s = int(abs(self.scale.counts_per_deg * config.max_velocity_deg_s)) or 1
        self._jump_margin_counts = max(4.0, self.scale.counts_per_deg)  # one degree
        self._has_torque = any(OD.TORQUE_ACTUAL in p.indexes for p in self.plan.tpdos)
        self._layouts = {p.cob_id: TpdoLayout.from_map(p) for p in self.plan.tpdos}
        for cob in self._layouts:
            network.subscribe(cob, self._on_tpdo)
        network.subscribe(0x700 + self.node_id, self._on_heartbeat)
        network.subscribe(0x80 + self.node_id, self._on_emcy)

    # ------------------------------------------------------------------ receive (hot path)
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

    # ------------------------------------------------------------------ supervision (driver's threads)
    def check_heartbeat(self, now: float) -> None:
        """Supervisor: declare the drive lost when its heartbeat is overdue."""
        if self.booted and not self.lost and self.last_heartbeat and \
                now - self.last_heartbeat > self.config.heartbeat_timeout_s:
            self.lost = True
            self.velocity_commanded = False
            logger.error("node %d (%s): heartbeat lost (none for %.0f ms, consumer time %.0f ms)",
                         self.node_id, self.name, (now - self.last_heartbeat) * 1000,
                         self.config.heartbeat_timeout_s * 1000)

    def set_foreign_master(self, evidence: str) -> bool:
        """Supervisor: another master drives this drive ("" once it has been gone long enough).
        A drive this driver had enabled gets a quick stop (nothing else of this driver's goes to
        it meanwhile); when it clears, the drive is configured again (not enabled): the other
        master may have reset or re-mapped it. True when the quick stop went out as an RPDO: the
        caller sends it by SDO as well (:meth:`quick_stop_by_sdo`, on the bus worker), since a
        drive the other master put in PRE-OPERATIONAL ignores PDOs and would keep moving."""
        stopped = False
        if evidence and not self.foreign_master:
            logger.error("%s (node %d): another master on the bus: %s; commands are refused", self.name,
                         self.node_id, evidence)
            if self.was_enabled and self.state == State.OPERATION_ENABLED:
                # two masters on one drive is no state to keep moving in: the last thing this
                # driver sends it is a quick stop (the watchdog no longer runs for it)
                stopped = True
                try:
                    self._stop_frame(Command.QUICK_STOP, "another master on the bus")
                except MotorError as err:
                    logger.error("%s: quick stop on losing control not sent: %s", self.name, err)
            self.velocity_commanded = False
            self.was_enabled = False
        elif not evidence and self.foreign_master:
            logger.warning("%s (node %d): the other master is gone; configuring the drive again (not enabled)",
                           self.name, self.node_id)
            self.booted = False
            self.rebooted.set()
        self.foreign_master = evidence
        return stopped

    def _disarm_by_sdo(self) -> None:
        """Boot: a drive found powered (configured without a reset after another master had it,
        or left enabled by a driver that did not stop it) is quick-stopped and disabled before
        anything else, by SDO (no PDOs flow before NMT start): a boot never leaves a drive armed
        behind a driver that says it is not enabled."""
        state = decode_state(int(self.sdo_read_value(OD.STATUSWORD)))  # type: ignore[arg-type]
        if state not in (State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            return
        logger.warning("%s (node %d): found %s at boot (another master, or a driver that did not stop it);"
                       " quick stop, then disable voltage", self.name, self.node_id, state.name)
        if state == State.OPERATION_ENABLED:
            self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        if state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):  # no power off while it brakes
            # stopped: Switch On Disabled (quick-stop options 1-3), or Quick Stop Active with
            # bit 10 set (options 5-7 hold there)
            self._poll_state_sdo(lambda st, sw: st == State.SWITCH_ON_DISABLED or (
                st == State.QUICK_STOP_ACTIVE and bool(sw & SW.TARGET_REACHED)), "quick stop at boot")
        self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.DISABLE_VOLTAGE)))
        self._poll_state_sdo(lambda st, sw: st == State.SWITCH_ON_DISABLED, "disable voltage at boot")

    def _poll_state_sdo(self, done: Callable[[State, int], bool], doing: str) -> None:
        deadline = time.monotonic() + TRANSITION_TIMEOUT_S
        while True:
            sw = int(self.sdo_read_value(OD.STATUSWORD))  # type: ignore[arg-type]
            if done(decode_state(sw), sw):
                self.statusword = sw
                return
            if time.monotonic() > deadline:
                raise DriveTimeoutError(f"{self.name} (node {self.node_id}): {doing}: still in"
                                        f" {decode_state(sw).name} (statusword 0x{sw:04X}) after"
                                        f" {TRANSITION_TIMEOUT_S:g} s", node_id=self.node_id, statusword=sw)
            time.sleep(0.02)

    def quick_stop_by_sdo(self, since: float) -> None:
        """Bus worker: the quick stop of losing control once more, as an SDO write of the
        controlword, where the RPDO cannot have reached the drive: its first heartbeat after
        ``since`` (when the other master was noticed) says PRE-OPERATIONAL. Not to a drive that
        reset meanwhile (a boot-up: the reset disabled it) or is still OPERATIONAL (it took the
        RPDO): the other master's SDO transfers use the same channel, and a needless write of
        ours breaks them (seen: a second driver's boot failed on our response). A reset is a
        boot-up after the drive's last OPERATIONAL heartbeat: it can come before the supervisor
        noticed the other master."""
        deadline = since + self.config.heartbeat_timeout_s  # a heartbeat by then, or the drive is lost
        while self.last_heartbeat <= since and time.monotonic() < deadline:
            time.sleep(0.01)
        if self._bootup_at > self._operational_at or self._reported_nmt != "PRE_OPERATIONAL":
            return
        try:
            self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.error("%s: quick stop by SDO on losing control failed: %s", self.name, err)

    def mark_lost(self) -> None:
        """Supervisor: the drive's bus is gone; nothing is commanded until it is booted again."""
        self.lost = True
        self.booted = False
        self.velocity_commanded = False
        self.was_enabled = False

    def reconfigure(self) -> None:
        """Bus worker: configure a drive that reset or power-cycled (boot-up seen) again; enable
        it again only when it was enabled and the config says ``restore_enable_after_reboot``."""
        restore = self.was_enabled and self.config.restore_enable_after_reboot
        self.was_enabled = False
        try:
            self.boot(reset=False)
            if restore and not self.closed:
                self.enable()
        except MotorError as err:
            logger.error("%s: re-configuration after a reset failed: %s; retrying in %g s", self.name, err,
                         REBOOT_RETRY_S)
            time.sleep(REBOOT_RETRY_S)
            self.rebooted.set()  # the supervisor hands it to the worker again

    # ------------------------------------------------------------------ snapshot
    @property
    def busy(self) -> str | None:
        """The operation in progress (enable, home, a stop, ...), or None: commands are refused meanwhile."""
        return self._busy

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
        error_code = emcy.code if emcy is not None and state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else 0
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
            fault=state in (State.FAULT, State.FAULT_REACTION_ACTIVE) or self.lost,
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

    # ------------------------------------------------------------------ SDO
    @contextmanager
    def _sdo_errors(self, what: str, index: int, subindex: int) -> Iterator[None]:
        """canopen's SDO exceptions -> this project's, with the abort code and its meaning; a
        malformed answer (canopen's parsing raising anything) is an SdoError too, never a
        struct.error reaching the caller."""
        where = f"node {self.node_id}: SDO {what} 0x{index:04X}:{subindex}"
        try:
            yield
        except canopen.SdoAbortedError as err:
            raise SdoError(f"{where} aborted with 0x{err.code:08X} ({sdo_abort_text(err.code)})",
                           node_id=self.node_id, index=index, subindex=subindex, abort_code=err.code) from err
        except canopen.SdoCommunicationError as err:
            if "No SDO response" not in str(err):  # an answer came, but not a valid one
                raise SdoError(f"{where}: the drive answered wrongly ({err}); the transfer was aborted",
                               node_id=self.node_id, index=index, subindex=subindex) from err
            raise SdoTimeoutError(f"{where} got no answer ({err}); check power, node id, bitrate and termination",
                                  node_id=self.node_id, index=index, subindex=subindex) from err
        except (can.CanError, OSError) as err:
            raise BusLostError(f"{where}: the bus is gone ({err})") from err
        except (struct.error, ValueError, IndexError, KeyError, TypeError) as err:
            raise SdoError(f"{where}: malformed answer from the drive ({type(err).__name__}: {err})",
                           node_id=self.node_id, index=index, subindex=subindex) from err

    def sdo_read(self, index: int, subindex: int = 0) -> bytes:
        """An SDO upload, bounded in size and in time: at most the object's size where its type
        has one (else SDO_UPLOAD_MAX_BYTES), and SDO_TRANSFER_TIMEOUTS x the SDO timeout in all,
        whatever the drive announces or keeps sending (a transfer past either is aborted)."""
        with self._sdo_errors("read", index, subindex):
            return self._bounded_upload(index, subindex)

    def _bounded_upload(self, index: int, subindex: int) -> bytes:
        var = variable(self.od, index, subindex)
        fixed = len(var) // 8 if var is not None and var.fixed_size else None
        cap = max(8, fixed) if fixed else SDO_UPLOAD_MAX_BYTES  # some drives send a U32 for a smaller type
        sdo = self.node.sdo
        where = f"node {self.node_id}: SDO read 0x{index:04X}:{subindex}"
        deadline = time.monotonic() + SDO_TRANSFER_TIMEOUTS * self.config.sdo_timeout_s
        data = bytearray()
        with sdo.open(index, subindex, buffering=0) as stream:
            if stream.size is not None and stream.size > cap:
                sdo.abort(SDO_ABORT_OUT_OF_MEMORY)
                raise SdoError(f"{where}: the drive announced {stream.size} bytes, more than the {cap} this object"
                               " can hold; the transfer was aborted", node_id=self.node_id, index=index,
                               subindex=subindex)
            while chunk := stream.read(7):
                data += chunk
                if len(data) > cap:
                    sdo.abort(SDO_ABORT_OUT_OF_MEMORY)
                    raise SdoError(f"{where}: the drive sent more than {cap} bytes; the transfer was aborted",
                                   node_id=self.node_id, index=index, subindex=subindex)
                if time.monotonic() > deadline:
                    sdo.abort(SDO_ABORT_TIMEOUT)
                    raise SdoTimeoutError(f"{where}: the transfer took over {SDO_TRANSFER_TIMEOUTS} x the SDO timeout"
                                          f" ({self.config.sdo_timeout_s:g} s); aborted", node_id=self.node_id,
                                          index=index, subindex=subindex)
        return bytes(data[:fixed] if fixed and len(data) > fixed else data)

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        with self._sdo_errors("write", index, subindex):
            self.node.sdo.download(index, subindex, data)

    def sdo_write_checked(self, index: int, subindex: int, value: int) -> None:
        """SDO write for tools and services: refuses the objects that move the motor or set its
        limits and PDOs, which only the driver's own checked paths may write."""
        reason = protected_reason(index)
        if reason is not None:
            raise CommandRejected(f"{self.name}: writing 0x{index:04X} by SDO is refused: {reason}.")
        self._write_typed(index, subindex, value)

    def sdo_read_value(self, index: int, subindex: int = 0) -> int | float | bytes:
        raw = self.sdo_read(index, subindex)
        var = variable(self.od, index, subindex)
        fmt = STRUCT_FORMAT.get(int(var.data_type)) if var is not None else None
        if fmt is not None and len(raw) == struct.calcsize(fmt):
            return struct.unpack(fmt, raw)[0]  # type: ignore[no-any-return]
        return raw

    def _write_typed(self, index: int, subindex: int, value: int) -> None:
        var = variable(self.od, index, subindex)
        fmt = STRUCT_FORMAT.get(int(var.data_type)) if var is not None else "<i"
        if fmt in ("<f", "<d"):
            self.sdo_write(index, subindex, struct.pack(fmt, float(value)))
        else:
            self.sdo_write(index, subindex, struct.pack(fmt or "<i", value))

    def _write_setting(self, setting: SdoSetting) -> None:
        """One entry of the config's ``sdo:`` list: typed by the EDS (or ``size`` bytes), read
        back when ``check``. Objects the driver owns are refused with the reason."""
        where = f"sdo setting 0x{setting.index:04X}:{setting.sub}"
        reason = protected_reason(setting.index)
        if reason is not None:
            raise BootError(f"node {self.node_id} ({self.name}): {where} is refused: {reason}.", node_id=self.node_id,
                            step="sdo settings", index=setting.index, subindex=setting.sub)
        var = variable(self.od, setting.index, setting.sub)
        fmt = STRUCT_FORMAT.get(int(var.data_type)) if var is not None else None
        if fmt is None and setting.size is None:
            raise BootError(f"node {self.node_id} ({self.name}): {where} is not in the drive's EDS; give its size"
                            " (size: 1, 2, 4 or 8 bytes) in the config", node_id=self.node_id, step="sdo settings",
                            index=setting.index, subindex=setting.sub)
        try:
            if fmt is not None:
                data = struct.pack(fmt, float(setting.value) if fmt in ("<f", "<d") else int(setting.value))
            else:
                size = int(setting.size or 4)
                data = int(setting.value).to_bytes(size, "little", signed=int(setting.value) < 0)
        except (struct.error, OverflowError) as err:
            raise BootError(f"node {self.node_id} ({self.name}): {where}: value {setting.value} does not fit the"
                            f" object ({fmt or f'{setting.size} bytes'}): {err}", node_id=self.node_id,
                            step="sdo settings", index=setting.index, subindex=setting.sub) from err
        self.sdo_write(setting.index, setting.sub, data)
        if setting.check:
            back = self.sdo_read(setting.index, setting.sub)[:len(data)]
            if back != data:
                raise BootError(f"node {self.node_id} ({self.name}): {where}: wrote {data.hex(' ')}, read back"
                                f" {back.hex(' ')}; the drive did not keep the value (range, or writable only in"
                                " another state?)", node_id=self.node_id, step="sdo settings",
                                index=setting.index, subindex=setting.sub)

    # ------------------------------------------------------------------ boot
    def boot(self, *, reset: bool = True) -> None:
        """Reset (NMT), check identity, configure PDOs and parameters, NMT start. Does not enable."""
        cfg = self.config
        step = "boot-up"
        self.booted = False
        self._supported_modes = None  # a replaced drive may support other modes
        self.rebooted.clear()
        if reset:
            self._note_host_loss_stop()
            self._bootup.clear()
            self._send(0x000, bytes([NmtCommand.RESET_NODE, self.node_id]))
            if not self._bootup.wait(cfg.boot_timeout_s):
                raise BootError(f"node {self.node_id} ({self.name}): no boot-up message within"
                                f" {cfg.boot_timeout_s:g} s after NMT reset (boot_timeout_ms); check power, node id,"
                                " bitrate and termination", node_id=self.node_id, step=step)
        current: tuple[int, int] = (0, 0)
        try:
            step = "identity"
            current = (OD.IDENTITY, 1)
            self._check_identity()
            step = "device type"
            current = (OD.DEVICE_TYPE, 0)
            device_type = struct.unpack("<I", self.sdo_read(OD.DEVICE_TYPE, 0)[:4].ljust(4, b"\0"))[0]
            if device_type & 0xFFFF != CIA402_PROFILE:
                logger.warning("node %d: device type 0x%08X is not a CiA 402 drive profile",
                               self.node_id, device_type)
            step = "disarm"
            if has_object(self.od, OD.STATUSWORD) and has_object(self.od, OD.CONTROLWORD):
                current = (OD.STATUSWORD, 0)
                self._disarm_by_sdo()
            step = "units"
            self._read_units()
            step = "PDO mapping"
            for index, sub, data, what in mapping_writes(self.plan):
                current = (index, sub)
                var = variable(self.od, index, sub)
                if var is not None and var.access_type in ("ro", "const"):
                    logger.info("node %d: %s: 0x%04X:%d is read-only in the EDS; keeping the device's"
                                " value", self.node_id, what, index, sub)
                    continue
                try:
                    self.sdo_write(index, sub, data)
                except SdoError as err:
                    raise BootError(f"node {self.node_id} ({self.name}): boot step '{step}' failed at"
                                    f" {what} (0x{index:04X}:{sub}): {err}", node_id=self.node_id,
                                    step=step, index=index, subindex=sub,
                                    abort_code=err.abort_code) from err
            step = "heartbeat"
            current = (OD.PRODUCER_HEARTBEAT_TIME, 0)
            self.guarding, self._guard_toggle = False, 0  # the toggle starts at 0 after a reset
            # CiA 301: a node with a heartbeat is not guarded; one that cannot be guarded here (no
            # remote frames) keeps its heartbeat, which tells the driver it is alive
            self._guardable = self.watch_mode() == "guarding" and self.remote_frames
            self.sdo_write(OD.PRODUCER_HEARTBEAT_TIME, 0,
                           struct.pack("<H", 0 if self._guardable else int(cfg.heartbeat_period_s * 1000)))
            step = "host watch"
            self._configure_host_watch()
            step = "position limits"
            if not cfg.is_continuous and has_object(self.od, OD.SOFTWARE_POSITION_LIMIT, 2):
                low, high = self.scale.limits_to_counts(cfg.min_deg, cfg.max_deg)  # type: ignore[arg-type]
                current = (OD.SOFTWARE_POSITION_LIMIT, 1)
                self._write_typed(OD.SOFTWARE_POSITION_LIMIT, 1, low)
                current = (OD.SOFTWARE_POSITION_LIMIT, 2)
                self._write_typed(OD.SOFTWARE_POSITION_LIMIT, 2, high)
            step = "profile parameters"
            to_drive, accel_to_drive = self.scale.magnitude_to_drive, self.scale.acceleration_to_drive
            for index, value in ((OD.PROFILE_VELOCITY, to_drive(cfg.profile_velocity_deg_s)),
                                 (OD.PROFILE_ACCELERATION, accel_to_drive(cfg.profile_acceleration_deg_s2)),
                                 (OD.PROFILE_DECELERATION, accel_to_drive(cfg.profile_acceleration_deg_s2)),
                                 (OD.MAX_PROFILE_VELOCITY, to_drive(cfg.max_velocity_deg_s))):
                if has_object(self.od, index):
                    current = (index, 0)
                    self._write_typed(index, 0, value)
            if has_object(self.od, OD.QUICK_STOP_DECELERATION):
                current = (OD.QUICK_STOP_DECELERATION, 0)
                self._write_typed(OD.QUICK_STOP_DECELERATION, 0, self._quick_stop_decel())
            step = "sdo settings"
            for setting in cfg.sdo:
                current = (setting.index, setting.sub)
                self._write_setting(setting)
            step = "operation mode"
            current = (OD.SUPPORTED_DRIVE_MODES, 0)
            supported = self.supported_modes()
            current = (OD.MODES_OF_OPERATION, 0)
            if supported >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_POSITION] & 1:
                self._switch_mode_sdo(OperationMode.PROFILE_POSITION)
            else:
                logger.warning("node %d (%s): 0x6502 = 0x%08X lists no profile position mode; the"
                               " drive boots without a mode; move_to() will be refused (stream_position uses IP where listed)",
                               self.node_id, self.name, supported)
                self.mode_display = int(self.sdo_read_value(OD.MODES_OF_OPERATION_DISPLAY))  # type: ignore[arg-type]
            step = "read state"
            current = (OD.STATUSWORD, 0)
            self.statusword = int(self.sdo_read_value(OD.STATUSWORD))  # type: ignore[arg-type]
            current = (OD.POSITION_ACTUAL, 0)
            self.position_counts = int(self.sdo_read_value(OD.POSITION_ACTUAL))  # type: ignore[arg-type]
            self._position_t = 0.0  # trust the next TPDO: the position was just read
            self._target_counts = self.position_counts
        except BootError:
            raise
        except (SdoError, DriveStateError) as err:
            code = getattr(err, "abort_code", None)
            raise BootError(f"node {self.node_id} ({self.name}): boot step '{step}' failed at"
                            f" 0x{current[0]:04X}:{current[1]}: {err}", node_id=self.node_id,
                            step=step, index=current[0], subindex=current[1], abort_code=code) from err
        try:
            self.safety = tuple(judge(cfg, self.host_node_id, self.scale, self._read_int,
                                      consumer_subs=consumer_subs(self.od), guarding=self._guardable))
        except SdoError as err:
            raise BootError(f"node {self.node_id} ({self.name}): boot step 'safety check' failed: {err}",
                            node_id=self.node_id, step="safety check", index=err.index, subindex=err.subindex,
                            abort_code=err.abort_code) from err
        for check in self.safety:
            if check.failed:
                logger.error("node %d (%s): safety check failed: %s: %s is %s, expected %s", self.node_id,
                             self.name, check.check, check.object, check.actual, check.expected)
        self._send(0x000, bytes([NmtCommand.START, self.node_id]))
        self.nmt_state = "OPERATIONAL"
        self.last_heartbeat = time.monotonic()
        self.lost = False
        self._cw = 0
        self.boot_count += 1
        self.fault_seen = None
        self.booted = True
        logger.info("node %d (%s) booted: %d RPDOs, %d TPDOs%s", self.node_id, self.name,
                    len(self.plan.rpdos), len(self.plan.tpdos),
                    f"; by SDO: {', '.join(f'0x{i:04X}' for i in self.plan.sdo_only)}"
                    if self.plan.sdo_only else "")

    def _configure_host_watch(self) -> None:
        """Tell the drive to stop by itself when the host falls silent (CiA 301 0x1016, CiA 402
        0x6007 and 0x605A): the one stop that holds when this process is killed, hung or unpowered."""
        cfg = self.config
        self.host_watch = None
        self.host_watch_problem = f"{NO_HOST_WATCH}: the drive has no consumer heartbeat time (0x1016)"
        if has_object(self.od, OD.QUICK_STOP_OPTION):
            self._write_typed(OD.QUICK_STOP_OPTION, 0, QUICK_STOP_THEN_DISABLE)
        if has_object(self.od, OD.ABORT_CONNECTION_OPTION):
            self._write_typed(OD.ABORT_CONNECTION_OPTION, 0, ON_HOST_LOSS[cfg.on_host_loss])
        if self.watch_mode() == "guarding":
            self._configure_guarding()
        elif has_object(self.od, OD.CONSUMER_HEARTBEAT_TIME, 1) and cfg.host_timeout_s is not None:
            entry = host_consumer_entry(self.host_node_id, cfg.host_timeout_s)
            try:
                self.sdo_write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", entry))
            except SdoError as err:
                if err.abort_code not in VALUE_RANGE_ABORTS:
                    raise
                self.host_watch_problem = (f"{NO_HOST_WATCH}: node {self.node_id} refuses 0x1016:1 = 0x{entry:08X}"
                                           f" (watch node {self.host_node_id}): {sdo_abort_text(err.abort_code or 0)}")
            else:
                reaction = cfg.on_host_loss if has_object(self.od, OD.ABORT_CONNECTION_OPTION) else \
                    "the drive's own reaction (no 0x6007 to choose it)"
                self.host_watch = (f"heartbeat consumer 0x1016:1 watches node {self.host_node_id}"
                                   f" ({cfg.host_timeout_s * 1000:.0f} ms), then {reaction}")
                self.host_watch_problem = None
        if self.host_watch is None and cfg.allow_no_host_watch:
            logger.warning("node %d (%s): %s; allowed by allow_no_host_watch: if this process dies, hangs or"
                           " loses power while the drive is enabled, NOTHING stops it", self.node_id, self.name,
                           self.host_watch_problem)
        elif self.host_watch is None:
            logger.warning("node %d (%s): %s; it will not be enabled (allow_no_host_watch: true overrides)",
                           self.node_id, self.name, self.host_watch_problem)

    def watch_mode(self) -> str:
        """How this drive watches the host: ``heartbeat`` (0x1016) or ``guarding`` (0x100C/0x100D);
        ``auto`` takes the heartbeat consumer where the drive has one."""
        mode = self.config.host_watch
        if mode == "auto":
            guardable = has_object(self.od, OD.GUARD_TIME) and has_object(self.od, OD.LIFE_TIME_FACTOR)
            mode = "guarding" if guardable and not has_object(self.od, OD.CONSUMER_HEARTBEAT_TIME, 1) else "heartbeat"
        return mode

    def _configure_guarding(self) -> None:
        """Node guarding: guard time and life time factor written; the supervisor guards the drive
        from then on (never a kernel timer: a hung process must fall silent)."""
        cfg = self.config
        if not (has_object(self.od, OD.GUARD_TIME) and has_object(self.od, OD.LIFE_TIME_FACTOR)):
            self.host_watch_problem = f"{NO_HOST_WATCH}: host_watch: guarding, but the drive has no 0x100C/0x100D"
            return
        if not self.remote_frames:
            self.host_watch_problem = (f"{NO_HOST_WATCH}: node guarding needs remote frames, which this bus cannot"
                                       " carry (socketcand's rawmode has none); use a kernel bus (socketcan)")
            return
        guard_ms, factor = guard_settings(cfg)
        self._write_typed(OD.GUARD_TIME, 0, guard_ms)
        self._write_typed(OD.LIFE_TIME_FACTOR, 0, factor)
        reaction = cfg.on_host_loss if has_object(self.od, OD.ABORT_CONNECTION_OPTION) else \
            "the drive's own reaction (no 0x6007 to choose it)"
        self.host_watch = (f"node guarding every {guard_ms} ms, life time {guard_ms * factor} ms (0x100C x 0x100D),"
                           f" then {reaction}")
        self.host_watch_problem = None
        self._next_guard = 0.0
        self.guarding = True

    def guard(self, now: float) -> None:
        """Supervisor: the guard (a remote frame on 0x700 + id) when one is due. Its answer is the
        drive's 'heartbeat': a missing one makes the drive lost after heartbeat_timeout_ms."""
        if not self.guarding or now < self._next_guard:
            return
        self._next_guard = max(self._next_guard + self.config.heartbeat_period_s, now)
        try:
            self.network.send_message(0x700 + self.node_id, b"", remote=True)
        except (can.CanError, OSError, RuntimeError) as err:  # a lost bus is the supervisor's to find
            logger.debug("node %d: guard not sent: %s", self.node_id, err)

    def _quick_stop_decel(self) -> int:
        """The configured quick-stop deceleration in drive units, at most what the drive takes
        (its EDS HighLimit): the fastest stop it allows, said in a warning."""
        wanted = self.scale.acceleration_to_drive(self.config.quick_stop_decel_deg_s2)
        var = variable(self.od, OD.QUICK_STOP_DECELERATION, 0)
        high = var.max if var is not None else None
        if isinstance(high, int) and wanted > high:
            logger.warning("node %d (%s): quick-stop deceleration %g deg/s^2 is beyond the drive's range"
                           " (0x6085 <= %d); using its maximum, %.0f deg/s^2", self.node_id, self.name,
                           self.config.quick_stop_decel_deg_s2, high, high * self.config.quick_stop_decel_deg_s2 / wanted)
            return high
        return wanted

    def _note_host_loss_stop(self) -> None:
        """Before the reset at boot: did the drive stop itself because the host was gone (the
        newest entry of its error history 0x1003 is 0x8130)? Counted for the flight recorder
        (``host_loss_stops``), and the history is cleared so that it is counted once. Only a
        drive heard within HOST_LOSS_CHECK_WAIT_S is asked: an absent one does not slow the boot."""
        if not has_object(self.od, OD.PREDEFINED_ERROR_FIELD, 1):
            return
        deadline = time.monotonic() + HOST_LOSS_CHECK_WAIT_S
        while not self.last_heartbeat and time.monotonic() < deadline:
            time.sleep(STATE_POLL_S)
        if not self.last_heartbeat:
            return
        try:
            self._check_identity()  # never clear the history of another drive than the config's
            newest = self._read_int(OD.PREDEFINED_ERROR_FIELD, 1)
            if newest is None or newest & 0xFFFF != EMCY_HOST_LOST:
                return
            self.host_loss_stops += 1
            logger.warning("node %d (%s): it had stopped itself when the host was lost (0x8130 in its error"
                           " history)", self.node_id, self.name)
            self.sdo_write(OD.PREDEFINED_ERROR_FIELD, 0, b"\x00")  # CiA 301: 0 clears the history
        except MotorError as err:
            logger.info("node %d (%s): error history not read before the reset: %s", self.node_id, self.name, err)

    def _read_int(self, index: int, subindex: int) -> int | None:
        """An integer object read by SDO, or None where the drive's EDS has no such object."""
        if not has_object(self.od, index, subindex):
            return None
        value = self.sdo_read_value(index, subindex)
        return int(value) if isinstance(value, (int, float)) else None

    def release_host_watch(self) -> None:
        """Clean shutdown of a disabled drive: stop watching the host, so that its last heartbeat
        raises no EMCY. Kept on a drive that is still enabled (the watch is then its only stop)."""
        if self.host_watch is None or self.lost or self.state == State.OPERATION_ENABLED:
            return
        if self.guarding:
            self._write_typed(OD.LIFE_TIME_FACTOR, 0, 0)  # 0: life guarding off
            self.guarding = False
        else:
            self.sdo_write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0))
        self.host_watch = None

    def _read_optional(self, index: int, subindex: int) -> bytes | None:
        """An object read by SDO whatever the EDS lists, or None where the drive aborts (it has
        no such object). No answer at all is an error, not an absence."""
        try:
            return self.sdo_read(index, subindex)
        except SdoTimeoutError:
            raise
        except SdoError:
            return None

    def _read_units(self) -> None:
        """Scale from the drive's own unit objects (factor group, SI units, rated torque), each
        read by SDO whatever the EDS lists: an EDS that omits 0x60A9 does not make an EPOS4's
        rpm counts/s. What came from where is said once at INFO (a conflict with the config at
        WARNING); later boots say it at DEBUG."""
        cfg = self.config
        objects = read_unit_objects(self._read_optional)
        self.scale, notes = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm, objects,
                                               invert=cfg.invert, offset_deg=cfg.offset_deg)
        self._max_counts_s = int(abs(self.scale.counts_per_deg * cfg.max_velocity_deg_s)) or 1
        self._jump_margin_counts = max(4.0, self.scale.counts_per_deg)
        for note in notes:
            level = logging.WARNING if "(config says" in note else logging.INFO
            logger.log(level if not self.boot_count else logging.DEBUG, "node %d (%s): %s", self.node_id,
                       self.name, note)

    def _require_resolution(self, doing: str) -> None:
        """Motion needs the position resolution from the config or the drive, never an assumption."""
        if not self.scale.resolution_known:
            raise CommandRejected(f"{self.name} (node {self.node_id}): {doing} refused: the position resolution is"
                                  " unknown (no counts_per_rev in the config, no 0x608F or 0x60A8 on the drive), so"
                                  " degrees cannot be turned into the drive's units. Set counts_per_rev for this drive"
                                  " (bench: --counts-per-rev N). Nothing was sent.")

    def expected_identity(self) -> list[tuple[int, str, frozenset[int], str]]:
        """What 0x1018 must hold: (sub, what, values allowed, who says so), from the config's
        ``identity:`` and from the EDS: vendor and product of its [DeviceInfo] (or of its own 0x1018
        defaults, where a file disagrees with itself). Not for the project's generic EDS, which
        stands for any CiA 402 drive."""
        wanted: list[tuple[int, str, frozenset[int], str]] = []
        expected = self.config.identity
        for sub, what, want in ((1, "vendor id", expected.vendor_id), (2, "product code", expected.product_code),
                                (3, "revision", expected.revision)):
            if want is not None:
                wanted.append((sub, what, frozenset({want}), "the config expects"))
        eds = Path(self.config.eds)
        if eds.resolve() == GENERIC_EDS.resolve():
            return wanted
        info = self.od.device_information
        for sub, what, number, name in ((1, "vendor id", info.vendor_number, info.vendor_name),
                                        (2, "product code", info.product_number, info.product_name)):
            var = variable(self.od, OD.IDENTITY, sub)
            values = {v for v in (number, var.default if var is not None else None) if isinstance(v, int) and v}
            if values:
                wanted.append((sub, what, frozenset(values), f"its EDS {eds.name}{f' ({name})' if name else ''} names"))
        return wanted

    def _check_identity(self) -> None:
        """0x1018 against the EDS and the config, before any other object of the drive is touched:
        a drive of another vendor or product at this node id is a boot error naming both ids."""
        for sub, what, allowed, source in self.expected_identity():
            raw = self._read_optional(OD.IDENTITY, sub) if sub > 1 else self.sdo_read(OD.IDENTITY, sub)
            if raw is None:
                logger.info("node %d (%s): no 0x1018:%d (%s) to compare", self.node_id, self.name, sub, what)
                continue
            got = struct.unpack("<I", raw[:4].ljust(4, b"\0"))[0]
            if got not in allowed:
                want = " or ".join(f"0x{v:08X}" for v in sorted(allowed))
                raise BootError(f"node {self.node_id} ({self.name}): identity mismatch: {what} is"
                                f" 0x{got:08X} on the device, {source} {want}. Is the right drive at this"
                                " node id, and is the config's EDS the drive's own? Nothing else was written to it.",
                                node_id=self.node_id, step="identity", index=OD.IDENTITY, subindex=sub)

    # ------------------------------------------------------------------ modes
    def supported_modes(self) -> int:
        """0x6502 as the drive reports it (read by SDO once per boot; all modes without it)."""
        if self._supported_modes is None:
            if not has_object(self.od, OD.SUPPORTED_DRIVE_MODES):
                self._supported_modes = 0xFFFF_FFFF
            else:
                self._supported_modes = int(self.sdo_read_value(OD.SUPPORTED_DRIVE_MODES))  # type: ignore[arg-type]
        return self._supported_modes

    def _switch_mode_sdo(self, mode: OperationMode, generation: int | None = None) -> None:
        """0x6060 by SDO, then 0x6061 polled until it shows ``mode``. No lock is held: the caller
        marked the drive busy; a stop meanwhile preempts it (``generation``)."""
        if generation is not None:
            with self._lock:
                self._check_not_preempted(generation, f"mode switch to {mode.name}")
                self._target_counts = self.position_counts
                self._handshake.reset()
        self._write_typed(OD.MODES_OF_OPERATION, 0, int(mode))
        self._hook("mode switch: 0x6060 written")
        deadline = time.monotonic() + MODE_SWITCH_TIMEOUT_S
        while True:
            shown = int(self.sdo_read_value(OD.MODES_OF_OPERATION_DISPLAY))  # type: ignore[arg-type]
            if generation is not None:
                self._check_not_preempted(generation, f"mode switch to {mode.name}")
            if shown == mode:
                self.mode_display = shown
                return
            if time.monotonic() > deadline:
                raise DriveTimeoutError(f"node {self.node_id}: mode {mode.name} written to 0x6060 but"
                                        f" 0x6061 still shows {shown} after {MODE_SWITCH_TIMEOUT_S:g} s",
                                        node_id=self.node_id, statusword=self.statusword)
            time.sleep(STATE_POLL_S)

    def set_mode(self, mode: OperationMode | int) -> None:
        """Switch the mode of operation; refuses modes 0x6502 does not list; waits for 0x6061.
        The drive is busy meanwhile (commands refused at once, a stop preempts it); no lock is
        held across its SDO round trips."""
        mode = OperationMode(mode)
        bit = SUPPORTED_MODE_BIT.get(mode)
        supported = self.supported_modes()
        if bit is None or not supported >> bit & 1:
            raise CommandRejected(f"{self.name}: mode {mode.name} is not supported by node"
                                  f" {self.node_id} (0x6502 = 0x{supported:08X}); supported:"
                                  f" {', '.join(m.name for m, b in SUPPORTED_MODE_BIT.items() if supported >> b & 1)}")
        if self.mode_display == mode:
            return
        with self._operation("mode switch") as generation:
            self._switch_mode_sdo(mode, generation)

    # ------------------------------------------------------------------ state machine
    def _send_cw(self, cw: int) -> None:
        pdo = self.plan.rpdo_with(OD.CONTROLWORD)
        if pdo is None:
            self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", cw))
            return
        values: dict[int, int] = {OD.CONTROLWORD: cw, OD.TARGET_POSITION: self._target_counts, OD.TARGET_VELOCITY: 0}
        self._send(pdo.cob_id, encode_rpdo(pdo, values))

    def _wait_state(self, wanted: set[State], timeout_s: float, doing: str, *,
                    fault_ok: bool = False, generation: int | None = None) -> State:
        deadline = time.monotonic() + timeout_s
        with self._status_event:
            while True:
                state = self.state
                if generation is not None:  # before the wanted state: a stop that landed meanwhile wins
                    self._check_not_preempted(generation, doing)
                if state in wanted:
                    return state
                if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) and not fault_ok:
                    raise self._fault_error(doing)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    hint = ""
                    if state == State.READY_TO_SWITCH_ON and not self.statusword & SW.VOLTAGE_ENABLED:
                        hint = " The drive reports no voltage: is STO low or the E-stop pressed?"
                    raise DriveTimeoutError(f"{self.name} (node {self.node_id}): {doing}: still in"
                                            f" {state.name} (statusword 0x{self.statusword:04X}) after"
                                            f" {timeout_s:g} s.{hint}", node_id=self.node_id,
                                            statusword=self.statusword)
                self._status_event.wait(min(remaining, 0.05))

    def _fault_error(self, doing: str) -> DriveStateError:
        emcy = self.last_emcy
        code = emcy.code if emcy is not None else None
        what = f"EMCY 0x{code:04X} {emcy_text(code)}" if code else "no EMCY received"
        return DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is in FAULT"
                               f" ({what}); call recover() to reset it", node_id=self.node_id,
                               statusword=self.statusword, error_code=code)

    @contextmanager
    def _operation(self, name: str, *, preempt: bool = False) -> Iterator[int]:
        """A state-machine operation that waits for the drive (enable, homing, a stop): the drive
        is marked busy with it instead of its lock being held while it waits, so a command
        meanwhile is refused at once (never queued behind seconds of waiting). ``preempt``:
        a stop, which does not wait for anyone; the operation it interrupts ends with an error.
        Yields the operation's generation (see :meth:`_check_not_preempted`)."""
        me = threading.get_ident()
        with self._lock:
            if self._busy and self._busy_owner != me and not preempt:
                raise CommandRejected(f"{self.name}: {name} refused: the drive is busy with {self._busy};"
                                      " nothing was sent. Try again when it is done.")
            outer = (self._busy, self._busy_owner)
            self._busy, self._busy_owner = name, me
            self._generation += 1
            generation = self._generation
            if preempt:
                self._preempted = (generation, name)  # every operation started before this one ends
        if preempt:
            with self._status_event:
                self._status_event.notify_all()  # an operation waiting for the drive notices at once
        try:
            yield generation
        finally:
            with self._lock:
                if self._busy_owner == me:
                    self._busy, self._busy_owner = outer

    def _check_not_preempted(self, generation: int, doing: str) -> None:
        if self.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver shut down meanwhile",
                                  node_id=self.node_id)
        before, by = self._preempted
        if generation < before:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} interrupted by {by}",
                                  node_id=self.node_id)

    @contextmanager
    def _command(self, name: str) -> Iterator[None]:
        """A command of a frame or two: the lock for at most COMMAND_LOCK_WAIT_S, and refused at
        once while an operation runs, so that a topic callback never waits on a service."""
        if not self._lock.acquire(timeout=COMMAND_LOCK_WAIT_S):
            raise CommandRejected(f"{self.name}: {name} refused: another command holds the drive;"
                                  " nothing was sent")
        try:
            self._refuse_if_busy(name)
            yield
        finally:
            self._lock.release()

    def _refuse_if_busy(self, doing: str) -> None:
        if self._busy and self._busy_owner != threading.get_ident():
            raise CommandRejected(f"{self.name}: {doing} refused: the drive is busy with {self._busy};"
                                  " nothing was sent. Send it again when that is done.")

    def _require_usable(self, doing: str) -> None:
        if self.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver is shut down;"
                                  " nothing was sent", node_id=self.node_id)
        if self.lost:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is lost (no"
                                  " heartbeat); nothing was sent", node_id=self.node_id)
        if self.foreign_master:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} refused: the drive is not under"
                                  f" this driver's control: another master is on the bus ({self.foreign_master})."
                                  " Stop the other driver or bench tool; this one configures the drive again"
                                  " (not enabled) once the bus is its own. Nothing was sent.", node_id=self.node_id)
        if not self.booted:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is not"
                                  " booted (boot() it, or wait for re-configuration after a reset)",
                                  node_id=self.node_id)

    def enable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Walk the state machine to Operation Enabled (transitions 2, 3, 4), holding position.

        Refused for a drive that cannot watch the host (no 0x1016), unless the config allows it.
        A stop (quick stop, disable, the driver's close) preempts it.
        """
        with self._operation("enable") as generation:
            self._require_usable("enable")
            self.fault_seen = None  # asked again: from here on a FAULT stops motion anew
            self._handshake.reset()  # a drive that left Operation Enabled acknowledges nothing more
            if self.host_watch is None and not self.config.allow_no_host_watch:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused: {self.host_watch_problem},"
                                      " so it would keep moving if this process were killed, hung or lost power."
                                      " Give it a heartbeat consumer, or set allow_no_host_watch: true for this"
                                      " drive (bench: --allow-no-host-watch) to arm it anyway. Nothing was sent.")
            self._target_counts = self.position_counts
            if self.state != State.OPERATION_ENABLED:
                self._clear_held_target()
            for _ in range(6):
                state = self.state
                if state == State.OPERATION_ENABLED:
                    if self._cw & ENABLED_CW_MASK != ENABLED_CW_MASK:  # enabled, but not by this driver's word
                        self._transition(generation, "enable", Command.ENABLE_OPERATION)
                    break
                if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    raise self._fault_error("enable")
                step = next_step_to_enable(state)
                if step is None:
                    self._wait_state({State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                                      State.SWITCHED_ON, State.OPERATION_ENABLED}, timeout_s, "enable",
                                     generation=generation)
                    continue
                target, number, command = step
                logger.debug("node %d: transition %d to %s", self.node_id, number, target.name)
                self._hook(f"enable: before transition {number}")
                self._transition(generation, f"enable (transition {number} to {target.name})", command)
                self._hook(f"enable: sent transition {number}")
                self._wait_state({target, State.OPERATION_ENABLED}, timeout_s,
                                 f"enable (transition {number} to {target.name})", generation=generation)
            with self._lock:  # the verdict and a stop are ordered too
                self._check_not_preempted(generation, "enable")
                if self.state != State.OPERATION_ENABLED:
                    raise DriveTimeoutError(f"{self.name}: could not reach OPERATION_ENABLED",
                                            node_id=self.node_id, statusword=self.statusword)
                self.was_enabled = True

    def _transition(self, generation: int, doing: str, command: Command | int, edge: int = 0) -> None:
        """One controlword of an operation (enable, recover, homing): the check that no stop came
        since the operation began and the frame are one critical section, so a stop's frame is
        always the last the drive gets."""
        with self._lock:
            self._check_not_preempted(generation, doing)
            self._cw = int(command)
            if self._cw & ENABLED_CW_MASK == ENABLED_CW_MASK:
                self._enable_sent_at = time.monotonic()
            self._send_cw(self._cw | edge)

    def _hook(self, point: str) -> None:
        """A seam for tests that force an interleaving: ``interleave`` is called at named points
        of the state machine (never set in production; None costs one attribute read)."""
        if self.interleave is not None:
            self.interleave(point)

    def _clear_held_target(self) -> None:
        """Before enabling: the drive still holds the last target from before a fault or a stop
        and follows it the moment it reaches Operation Enabled. Velocity and torque modes: a
        recovered wheel ran at its old 0x60FF (286 deg/s) until the watchdog; so 0 here. The
        cyclic position modes: a wheel stopped at speed brakes on past its last set-point
        (0x607A / 0x60C1:1) and jumped back to it (9 deg); so where the shaft is now (0x6064,
        read now: the braked shaft does not move). By SDO: the RPDO that carries the target
        also carries the controlword "enable operation"."""
        mode = self.mode_display
        if mode in VELOCITY_MODES:
            self._write_typed(OD.TARGET_VELOCITY, 0, 0)
        elif mode in TORQUE_MODES:
            self._write_typed(OD.TARGET_TORQUE, 0, 0)
        elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            actual = self._read_int(OD.POSITION_ACTUAL, 0)
            if actual is None:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused in"
                                      f" {OperationMode(mode).name}: the drive's EDS has no 0x6064, so its held"
                                      " set-point cannot be moved to where the shaft is. Nothing was sent.")
            self._target_counts = actual
            index, sub = (OD.TARGET_POSITION, 0) if mode == OperationMode.CYCLIC_SYNC_POSITION else \
                (OD.INTERPOLATION_DATA, 1)
            if has_object(self.od, index, sub):  # without it, nothing is held
                self._write_typed(index, sub, actual)

    def _stop(self, name: str, command: Command, wanted: set[State], timeout_s: float) -> None:
        """A stop: it preempts every operation under way, and its decision and its frame are one
        critical section (:meth:`_stop_frame`); the frame is always sent, since the state last
        seen may be stale while another frame is on its way. Then it waits for ``wanted`` (or a
        fault) without holding the lock."""
        with self._operation(name, preempt=True):
            self._stop_frame(command, name)
            self._hook(f"{name}: sent")
            self._wait_state(wanted | {State.FAULT, State.FAULT_REACTION_ACTIVE}, timeout_s, name)

    def _stop_frame(self, command: Command, by: str) -> None:
        """The frame of a stop, decided and sent under the lock: no command or transition can
        follow it unless it was decided after it. The set-point handshake is forgotten first, so
        the receive thread sends no "enable operation" reply after it."""
        with self._lock:
            self._generation += 1
            self._preempted = (self._generation, by)
            self.was_enabled = False
            self.velocity_commanded = False
            self._handshake.reset()
            self._cw = int(command)
            self._send_cw(self._cw)

    def disable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Shutdown (transition 8, 6 or 2): power stage off, drive in Ready to Switch On."""
        self._stop("disable", Command.SHUTDOWN, {State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED}, timeout_s)

    def quick_stop(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Quick stop (transition 11; 7 or 10 from the states before): the drive brakes on its
        quick-stop ramp."""
        self._stop("quick stop", Command.QUICK_STOP, {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED}, timeout_s)

    def disable_voltage(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Disable voltage (transitions 7, 9, 10, 12): power stage off, Switch On Disabled."""
        self._stop("disable voltage", Command.DISABLE_VOLTAGE, {State.SWITCH_ON_DISABLED}, timeout_s)

    def set_profile_velocity(self, velocity_deg_s: float) -> None:
        """The speed of the following profile-position moves (0x6081), at most max_velocity_deg_s."""
        speed = require_finite(f"{self.name} profile velocity", velocity_deg_s, "deg/s")
        self._require_resolution("a profile velocity")
        if not 0 < speed <= self.config.max_velocity_deg_s:
            raise CommandRejected(f"{self.name}: profile velocity {speed:g} deg/s: allowed 0 < speed <="
                                  f" {self.config.max_velocity_deg_s:g} (max_velocity_deg_s). Nothing was sent.")
        with self._operation("profile velocity"):  # an SDO round trip: busy, not the lock
            self._write_typed(OD.PROFILE_VELOCITY, 0, self.scale.magnitude_to_drive(speed))

    def halt(self, on: bool = True) -> None:
        """Set or clear the halt bit (8): stop on the profile deceleration, stay enabled."""
        with self._command("halt"):
            self._require_usable("halt")
            self._cw = (self._cw | CW.HALT) if on else (self._cw & ~CW.HALT)
            self._send_cw(self._cw)

    def recover(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Fault reset (transition 15), then back to the enable state the drive had before."""
        with self._operation("recover") as generation:
            self._require_usable("recover")
            restore = self.was_enabled
            if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                if self.state == State.FAULT_REACTION_ACTIVE:
                    self._wait_state({State.FAULT}, timeout_s, "recover (fault reaction)", fault_ok=True,
                                     generation=generation)
                self._transition(generation, "recover", 0)
                self._transition(generation, "recover", Command.FAULT_RESET)
                self._wait_state({State.SWITCH_ON_DISABLED}, timeout_s, "fault reset (transition 15)",
                                 fault_ok=True, generation=generation)
                self._transition(generation, "recover", 0)
            self.last_emcy = None
            self.fault_seen = None
            if restore:
                self.enable(timeout_s)

    # ------------------------------------------------------------------ motion
    def _position_target_counts(self, angle_deg: float) -> int:
        angle = require_finite(f"{self.name} angle", angle_deg, "deg")
        self._require_resolution("a position command")
        cfg = self.config
        if cfg.is_continuous:
            if abs(angle) > CONTINUOUS_COMMAND_LIMIT_DEG:
                raise CommandRejected(f"{self.name}: {angle:g} deg: a continuous joint takes an angle from"
                                      f" -{CONTINUOUS_COMMAND_LIMIT_DEG:g} to {CONTINUOUS_COMMAND_LIMIT_DEG:g} deg"
                                      " and moves the short way to it. Nothing was sent.")
            angle = nearest_equivalent(angle, self.angle_deg)
        else:
            check_limits(self.name, angle, cfg.min_deg, cfg.max_deg)
        return check_counts(self.name, self.scale.deg_to_counts(angle), "target position")

    def check_position(self, angle_deg: float) -> float:
        """The (multi-turn) angle a position command of ``angle_deg`` would go to, or
        :class:`CommandRejected` naming the limit; nothing is sent."""
        return self.scale.counts_to_deg(self._position_target_counts(angle_deg))

    def move_to(self, angle_deg: float, *, wait: bool = False, timeout_s: float | None = None) -> float:
        """Profile-position move to ``angle_deg``; returns the (multi-turn) target in degrees.

        A continuous joint takes the short way round; a limited joint refuses targets beyond
        its limits. Nothing is sent for a refused command.
        """
        counts = self._position_target_counts(angle_deg)
        self._ensure_mode(OperationMode.PROFILE_POSITION, "move")
        if self.plan.rpdo_with(OD.CONTROLWORD) is None:
            raise CommandRejected(f"{self.name} (node {self.node_id}): move refused: the controlword cannot be"
                                  " PDO-mapped on this drive, and the set-point handshake's replies come from the"
                                  " receive thread, which never waits for an SDO. Nothing was sent.")
        if self.plan.rpdo_with(OD.TARGET_POSITION) is None:
            # 0x607A only by SDO (the SCHUNK PRL120): written here, on the caller's thread and with
            # the drive busy (no lock held while the SDO waits); the handshake sends only the edge
            with self._operation("move (target by SDO)"):
                self._write_typed(OD.TARGET_POSITION, 0, counts)
                with self._lock:
                    self._require_motion(OperationMode.PROFILE_POSITION, "move")
                    self._cw &= ~CW.HALT
                    self._handshake.command(counts)
        else:
            with self._command("move"):
                self._require_motion(OperationMode.PROFILE_POSITION, "move")
                self._cw &= ~CW.HALT
                self._handshake.command(counts)
        if wait:
            self.wait_target_reached(timeout_s)
        return self.scale.counts_to_deg(counts)

    def _send_setpoint(self, counts: int) -> None:
        """A target with controlword bit 4 rising (called by the handshake, under its lock)."""
        self._target_counts = counts
        pdo = self.plan.rpdo_with(OD.TARGET_POSITION)
        cw = controlword(Command.ENABLE_OPERATION, new_setpoint=True, change_immediately=True)
        cw |= self._cw & CW.HALT
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw,
                                                                    OD.TARGET_POSITION: counts}))
        else:  # 0x607A not PDO-mappable (SCHUNK PRL120): move_to wrote it by SDO; the edge only
            self._send_cw(cw)

    def _clear_setpoint(self) -> None:
        """Controlword bit 4 back to 0 after the acknowledge (called by the handshake)."""
        self._send_cw(int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT))

    def wait_target_reached(self, timeout_s: float | None = None) -> None:
        if timeout_s is None:
            span = self.scale.span_deg(self._target_counts - self.position_counts)
            cfg = self.config
            timeout_s = 2.0 + span / cfg.profile_velocity_deg_s + 2 * cfg.profile_velocity_deg_s / cfg.profile_acceleration_deg_s2
        deadline = time.monotonic() + timeout_s
        with self._status_event:
            while True:
                if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    raise self._fault_error("move")
                if self._handshake.idle and self.statusword & SW.TARGET_REACHED:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DriveTimeoutError(f"{self.name}: target not reached within {timeout_s:.1f} s"
                                            f" (at {self.angle_deg:.2f} deg, target"
                                            f" {self.scale.counts_to_deg(self._target_counts):.2f} deg)",
                                            node_id=self.node_id, statusword=self.statusword)
                self._status_event.wait(min(remaining, 0.05))
        # the statusword comes on change, the position on SYNC: wait for a position sampled
        # after the drive said 'reached', so the caller's snapshot is not one period old
        seq = self._position_seq
        settle = time.monotonic() + 3 * self.sync_period_s + 0.05
        while self._position_seq == seq and time.monotonic() < settle:
            time.sleep(0.001)

    def set_velocity(self, velocity_deg_s: float) -> None:
        """Profile-velocity command in deg/s, limited by max_velocity_deg_s; feeds the watchdog."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.PROFILE_VELOCITY, "velocity command")
        with self._command("velocity command"):
            self._refuse_past_limit(velocity, abs(velocity), self.config.profile_acceleration_deg_s2,
                                    f"velocity {velocity:g} deg/s")
            self._require_motion(OperationMode.PROFILE_VELOCITY, "velocity command")
            self._send_velocity(counts_s)
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = velocity != 0.0

    # ------------------------------------------------------------------ limits in every mode
    def _limit_ahead(self, direction: float, speed_deg_s: float, decel_deg_s2: float,
                     torque_mode: bool = False) -> str | None:
        """The limit a motion in ``direction`` at ``speed_deg_s`` (or the joint's own speed, if
        higher) could not stop before when braking at ``decel_deg_s2``; None when clear.
        ``torque_mode``: nothing caps the joint's acceleration (a profile does in the velocity
        modes), so it speeds up on its measured acceleration while the guard reacts."""
        cfg = self.config
        if cfg.is_continuous or direction == 0 or cfg.min_deg is None or cfg.max_deg is None:
            return None
        velocity = self.scale.counts_s_to_deg_s(self.velocity_counts_s)
        accel = self.scale.counts_s_to_deg_s(self.accel_counts_s2) if torque_mode else 0.0
        accel = accel if accel * direction > 0 else 0.0  # only speeding up toward the limit counts
        age = min(max(time.time() - self.stamp, 0.0), MAX_EXTRAPOLATION_S) if self.stamp else 0.0
        # where the joint is now, and how fast, not when its TPDO was sampled
        angle = self.angle_deg + velocity * age + 0.5 * accel * age * age
        speed = max(speed_deg_s, abs(velocity + accel * age))
        gain = abs(accel) * LIMIT_ACCEL_MARGIN_S  # speed gained before the brake takes hold
        need = (speed + gain) ** 2 / (2 * decel_deg_s2) + speed * LIMIT_MARGIN_S + 0.5 * gain * LIMIT_ACCEL_MARGIN_S
        if direction > 0 and cfg.max_deg - angle <= need:
            return f"max_deg={cfg.max_deg:g}"
        if direction < 0 and angle - cfg.min_deg <= need:
            return f"min_deg={cfg.min_deg:g}"
        return None

    def _refuse_past_limit(self, direction: float, speed_deg_s: float, decel_deg_s2: float, what: str,
                           torque_mode: bool = False) -> None:
        limit = self._limit_ahead(direction, speed_deg_s, decel_deg_s2, torque_mode)
        if limit is None:
            return
        self._brake()
        raise CommandRejected(f"{self.name}: {what} refused: at {self.angle_deg:.2f} deg the joint could not stop"
                              f" before its limit {limit} braking at {decel_deg_s2:g} deg/s^2; it is stopping."
                              " Command away from the limit, or move_to() a target inside it.")

    def _brake(self) -> None:
        """Stop a velocity- or torque-commanded joint at once, without waiting: zero velocity
        (the drive brakes on its profile deceleration) or, in torque mode, a quick stop."""
        self.velocity_commanded = False
        if self.state != State.OPERATION_ENABLED:
            return
        self.limit_stops += 1
        if self.mode_display in VELOCITY_MODES:
            self._send_velocity(0)
        elif self.mode_display in TORQUE_MODES:
            self._send_torque(0)
            self._stop_frame(Command.QUICK_STOP, "the limit guard's quick stop")

    def guard_limits(self) -> None:
        """Supervisor, every period: brake a velocity- or torque-commanded limited joint whose
        stopping distance has reached its limit (the drive's own 0x607D is the backstop)."""
        if self.config.is_continuous or not self.velocity_commanded:
            return
        velocity = self.scale.counts_s_to_deg_s(self.velocity_counts_s)
        torque_mode = self.mode_display in TORQUE_MODES
        decel = self.config.quick_stop_decel_deg_s2 if torque_mode else self.config.profile_acceleration_deg_s2
        limit = self._limit_ahead(velocity, abs(velocity), decel, torque_mode)
        if limit is None:
            return
        # never waits (the supervisor's period is the host heartbeat's): a command that holds the
        # lock is checked against the limit itself, and the next period brakes if it still must
        if not self._lock.acquire(blocking=False):
            return
        try:
            logger.warning("%s: at %.2f deg moving %.1f deg/s toward its limit %s; braking", self.name,
                           self.angle_deg, velocity, limit)
            self._brake()
        finally:
            self._lock.release()

    def _send_velocity(self, counts_s: int) -> None:
        pdo = self.plan.rpdo_with(OD.TARGET_VELOCITY)
        cw = int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT)
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw,
                                                                    OD.TARGET_VELOCITY: counts_s}))
        else:
            self._write_typed(OD.TARGET_VELOCITY, 0, counts_s)

    def stop_velocity(self) -> bool:
        """Watchdog action: zero velocity (PV) or zero torque (PT). Never waits: when a command
        holds the drive (enable, homing, a mode switch: each ends the velocity command itself),
        it returns False and the supervisor tries again at its next period."""
        if not self._lock.acquire(blocking=False):
            return False
        try:
            if self._busy:
                return False
            self.velocity_commanded = False
            if self.state != State.OPERATION_ENABLED:
                return True
            if self.mode_display in VELOCITY_MODES:
                self._send_velocity(0)
                self.watchdog_stops += 1
            elif self.mode_display in TORQUE_MODES:
                self._send_torque(0)
                self.watchdog_stops += 1
            return True
        finally:
            self._lock.release()

    def _require_enabled(self, doing: str) -> None:
        self._require_usable(doing)
        if self.fault_seen is not None and self.state not in FAULT_STATES:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} refused: the drive reported FAULT"
                                  f" (statusword 0x{self.fault_seen:04X}) since it was enabled, though it shows"
                                  f" {self.state.name} now; recover() and enable() it again",
                                  node_id=self.node_id, statusword=self.statusword)
        if self.state != State.OPERATION_ENABLED or self._cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
            if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise self._fault_error(doing)
            shown = self.state.name if self.state != State.OPERATION_ENABLED else "stopping"
            raise DriveStateError(f"{self.name}: {doing} refused: the drive is {shown}; enable() it"
                                  " first", node_id=self.node_id, statusword=self.statusword)

    def _ensure_mode(self, mode: OperationMode, doing: str) -> None:
        """Before a motion command, without the lock: the drive enabled and in ``mode`` (a mode
        switch is an operation of its own, :meth:`set_mode`)."""
        self._refuse_if_busy(doing)
        self._require_enabled(doing)
        if self.mode_display != mode:
            self.set_mode(mode)

    def _require_motion(self, mode: OperationMode, doing: str) -> None:
        """Under the lock, right before a motion frame, decided with it as one step: the drive is
        usable, this driver's last controlword was Enable Operation (no stop since), the last
        statusword said Operation Enabled, and the mode is still ``mode``."""
        self._require_enabled(doing)
        if self.mode_display != mode:
            raise CommandRejected(f"{self.name}: {doing} refused: the drive left {mode.name} meanwhile (now"
                                  f" {self.mode_display}); nothing was sent. Send it again.")

    def _checked_torque(self, torque_nm: float) -> float:
        torque = require_finite(f"{self.name} torque", torque_nm, "Nm")
        self._require_resolution("a torque command")  # its limit guard works in degrees
        limit = self.config.max_torque_nm or self.scale.rated_torque_nm * self.scale.gear_ratio
        if abs(torque) > limit:
            raise CommandRejected(f"{self.name}: torque {torque:g} Nm is beyond the limit max_torque_nm={limit:g}"
                                  f" (allowed -{limit:g} to {limit:g} Nm). Nothing was sent.")
        return torque

    def _checked_velocity(self, velocity_deg_s: float) -> tuple[float, int]:
        velocity = require_finite(f"{self.name} velocity", velocity_deg_s, "deg/s")
        self._require_resolution("a velocity command")
        vmax = self.config.max_velocity_deg_s
        if abs(velocity) > vmax:
            raise CommandRejected(f"{self.name}: velocity {velocity:g} deg/s is beyond the limit"
                                  f" max_velocity_deg_s={vmax:g} (allowed -{vmax:g} to {vmax:g}). Nothing"
                                  " was sent.")
        return velocity, check_counts(self.name, self.scale.deg_s_to_counts_s(velocity), "velocity")

    def set_torque(self, torque_nm: float) -> None:
        """Profile-torque command in Nm at the joint, limited by max_torque_nm; feeds the watchdog."""
        torque = self._checked_torque(torque_nm)
        self._ensure_mode(OperationMode.PROFILE_TORQUE, "torque command")
        with self._command("torque command"):
            self._refuse_past_limit(torque, 0.0, self.config.quick_stop_decel_deg_s2, f"torque {torque:g} Nm",
                                    torque_mode=True)
            self._require_motion(OperationMode.PROFILE_TORQUE, "torque command")
            self._send_torque(self.scale.nm_to_permille(torque))
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = torque != 0.0

    def _send_torque(self, permille: int) -> None:
        pdo = self.plan.rpdo_with(OD.TARGET_TORQUE)
        cw = int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT)
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw, OD.TARGET_TORQUE: permille}))
        else:
            self._write_typed(OD.TARGET_TORQUE, 0, permille)

    def stream_velocity(self, velocity_deg_s: float) -> None:
        """Cyclic synchronous velocity (CSV): one target per SYNC period, which the drive takes
        at the next SYNC without a ramp of its own (the caller's stream is the ramp). Limited by
        max_velocity_deg_s; speeding up by more than the quick-stop deceleration over two SYNC
        periods in one step is refused (slowing down never is); feeds the watchdog. Refused on a
        drive whose 0x6502 does not list CSV."""
        velocity, counts_s = self._checked_velocity(velocity_deg_s)
        self._ensure_mode(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point")
        with self._command("CSV set-point"):
            self._refuse_past_limit(velocity, abs(velocity), self.config.quick_stop_decel_deg_s2,
                                    f"CSV velocity {velocity:g} deg/s")
            self._require_motion(OperationMode.CYCLIC_SYNC_VELOCITY, "CSV set-point")
            previous = self.scale.counts_s_to_deg_s(self._stream_velocity_counts_s) if self.velocity_commanded else 0.0
            max_step = self.config.quick_stop_decel_deg_s2 * 2 * self.sync_period_s
            if abs(velocity) > abs(previous) and abs(velocity - previous) > max_step:
                raise CommandRejected(f"{self.name}: CSV set-point {velocity:g} deg/s jumps"
                                      f" {abs(velocity - previous):.1f} deg/s from the last one ({previous:g});"
                                      f" at most {max_step:.1f} deg/s per step speeding up (the quick-stop"
                                      " deceleration over two SYNC periods). Ramp it. Nothing was sent.")
            self._send_velocity(counts_s)
            self._stream_velocity_counts_s = counts_s
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = velocity != 0.0

    def stream_torque(self, torque_nm: float) -> None:
        """Cyclic synchronous torque (CST): one torque target in Nm at the joint per SYNC period,
        limited by max_torque_nm; feeds the watchdog (which sends zero torque). Refused on a
        drive whose 0x6502 does not list CST."""
        torque = self._checked_torque(torque_nm)
        self._ensure_mode(OperationMode.CYCLIC_SYNC_TORQUE, "CST set-point")
        with self._command("CST set-point"):
            self._refuse_past_limit(torque, 0.0, self.config.quick_stop_decel_deg_s2, f"CST torque {torque:g} Nm",
                                    torque_mode=True)
            self._require_motion(OperationMode.CYCLIC_SYNC_TORQUE, "CST set-point")
            self._send_torque(self.scale.nm_to_permille(torque))
            self.last_velocity_cmd = time.monotonic()
            self.velocity_commanded = torque != 0.0

    def command_velocity(self, velocity_deg_s: float) -> None:
        """A velocity command in the drive's configured way: profile velocity, or CSV
        (``velocity_mode: cyclic``)."""
        if self.config.velocity_mode == "cyclic":
            self.stream_velocity(velocity_deg_s)
        else:
            self.set_velocity(velocity_deg_s)

    def command_torque(self, torque_nm: float) -> None:
        """A torque command in the drive's configured way: profile torque, or CST
        (``torque_mode: cyclic``)."""
        if self.config.torque_mode == "cyclic":
            self.stream_torque(torque_nm)
        else:
            self.set_torque(torque_nm)

    def stream_position(self, angle_deg: float, *, max_step_deg: float | None = None) -> None:
        """One position set-point per SYNC period, no handshake: cyclic synchronous position,
        or interpolated position (0x60C1:1, controlword bit 4 "enable ip mode") on a drive
        whose 0x6502 lists IP but not CSP (the SCHUNK PRL120 is one).

        Refuses a setpoint that jumps further than ``max_step_deg`` (default: max velocity
        over two SYNC periods) from the previous one: a streamed trajectory must be smooth.
        """
        counts = self._position_target_counts(angle_deg)
        mode = self._streaming_mode()
        doing = "CSP setpoint" if mode == OperationMode.CYCLIC_SYNC_POSITION else "IP setpoint"
        self._ensure_mode(mode, doing)
        with self._command("set-point"):
            self._require_motion(mode, doing)
            if max_step_deg is None:
                max_step_deg = self.config.max_velocity_deg_s * 2 * self.sync_period_s
            step = self.scale.span_deg(counts - self._target_counts)
            if step > max_step_deg:
                raise CommandRejected(f"{self.name}: CSP setpoint jumps {step:.3f} deg from the last one; at most"
                                      f" {max_step_deg:.3f} deg per step (max_velocity_deg_s over two SYNC"
                                      " periods) is allowed. Nothing was sent.")
            self._target_counts = counts
            cw = int(Command.ENABLE_OPERATION)
            target = OD.TARGET_POSITION
            if mode == OperationMode.INTERPOLATED_POSITION:
                cw |= CW.NEW_SETPOINT  # enable ip mode: the drive follows 0x60C1:1 at each SYNC
                target = OD.INTERPOLATION_DATA
            pdo = self.plan.rpdo_with(target)
            if pdo is not None:
                self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw, target: counts}))
            else:
                self._write_typed(target, 1 if target == OD.INTERPOLATION_DATA else 0, counts)
                self._send_cw(cw)

    def _streaming_mode(self) -> OperationMode:
        if self.mode_display in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            return OperationMode(self.mode_display)  # the hot path: streaming already
        supported = self.supported_modes()
        for mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            if supported >> SUPPORTED_MODE_BIT[mode] & 1:
                return mode
        raise CommandRejected(f"{self.name}: streaming set-points needs cyclic synchronous or interpolated"
                              f" position; node {self.node_id} supports neither (0x6502 = 0x{supported:08X}).")

    def home(self, timeout_s: float | None = None) -> None:
        """Homing with the configured method and speed; waits for 'homing attained'. The drive
        is busy meanwhile: commands are refused, a stop preempts it."""
        cfg = self.config
        self._require_resolution("homing")
        if not has_object(self.od, OD.HOMING_METHOD) or \
                not self.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.HOMING] & 1:
            raise CommandRejected(f"{self.name}: this drive has no homing mode ("
                                  f"{'no 0x6098 in its EDS' if not has_object(self.od, OD.HOMING_METHOD) else '0x6502 lists no homing'});"
                                  " nothing was sent. Home it with the vendor's tool, or set offset_deg in the config.")
        with self._operation("home") as generation:
            self._require_usable("home")
            self.set_mode(OperationMode.HOMING)
            self._write_typed(OD.HOMING_METHOD, 0, cfg.homing_method)
            if has_object(self.od, OD.HOMING_SPEEDS, 1):
                self._write_typed(OD.HOMING_SPEEDS, 1, self.scale.magnitude_to_drive(cfg.homing_speed_deg_s))
            if self.state != State.OPERATION_ENABLED:
                self.enable()
            self._transition(generation, "home", Command.ENABLE_OPERATION)
            self._transition(generation, "home", Command.ENABLE_OPERATION, edge=CW.NEW_SETPOINT)
            deadline = time.monotonic() + (timeout_s or cfg.homing_timeout_s)
            while True:
                sw = self.statusword
                if sw & SW.FOLLOWING_ERROR:
                    raise DriveStateError(f"{self.name}: homing error reported (statusword 0x{sw:04X})",
                                          node_id=self.node_id, statusword=sw)
                if sw & SW.SETPOINT_ACK and sw & SW.TARGET_REACHED:
                    break
                if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    raise self._fault_error("home")
                self._check_not_preempted(generation, "home")
                if time.monotonic() > deadline:
                    raise DriveTimeoutError(f"{self.name}: homing not attained within"
                                            f" {timeout_s or cfg.homing_timeout_s:g} s", node_id=self.node_id,
                                            statusword=sw)
                time.sleep(STATE_POLL_S)
            self._position_t = 0.0  # homing moves the zero: the next position is trusted as it comes
            seq = self._position_seq
            settle = time.monotonic() + 3 * self.sync_period_s + 0.05
            while self._position_seq == seq and time.monotonic() < settle:
                time.sleep(0.001)
            self._transition(generation, "home", Command.ENABLE_OPERATION)
            self.set_mode(OperationMode.PROFILE_POSITION)
            self._target_counts = self.position_counts

"""The bus as ROS 2 messages (pure, no rclpy): every frame, and with a config every drive decoded
by its EDS and the driver's PDO map, for MCAP files and the live Foxglove view.

:class:`BusView` takes frames (:data:`Frame`) of every bus, puts them in time order
(:class:`~motor_driver.recording.timemerge.TimeMerge`: a reader per bus hands them over in arrival order)
and hands out messages as plain dicts (``emit(topic, type, message, time_ns)``, types from
:mod:`motor_driver.recording.ros2defs`):

- ``/can/frames`` (rovercan_msgs/CanFrame): each frame, its bus, id, flags, data and time;
- ``/joint_states`` (sensor_msgs/JointState): every drive of the config, in its order, at the end
  of each SYNC cycle (every drive heard in the last one has sent each of its SYNC TPDOs, or one
  sends a second), stamped with the newest frame of it, as the driver publishes it: a drive's last
  angle (rad), velocity (rad/s) and torque (Nm), NaN only while its data is stale by its own
  frames' times (none for ``stale_after_syncs`` SYNC periods of its bus) or it was never heard;
- ``/drives/<name>/status`` (rovercan_msgs/DriveStatus): a drive's MotorState as the driver
  publishes it (angle wrapped on a continuous joint, ``stale`` and ``data_age`` from its frames'
  times), its statusword, controlword, mode, NMT state and EMCY, for each cycle its TPDOs came in;
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): what the flight recorder watches for (an
  EMCY, a boot-up, a heartbeat lost and back) when it is seen, and every drive once a second,
  judged by the live /diagnostics' own rules (:func:`drive_row`).

Every value is the driver's own conversion: its TPDO decoder and position filter
(:func:`motor_driver.drive.received.tpdo.decode_tpdo`), its units (:func:`motor_driver.protocol.units.scale_from_objects`:
the drive's unit objects as its SDO answers to the driver's boot show them on the bus, or as a
recording's metadata gives them, else the config's, which :meth:`BusView.units` says), its
verdict (:func:`motor_driver.drive.verdict.judge`) and its topics' conversion (:mod:`motor_driver.recording.published`).
Times are the frames' own. Owner: the one thread that feeds it.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from can_config.config import DriveConfig
from can_config.eds import load_drive_od
from can_config.errors import UnitError
from can_config.model import RoverConfig
from can_config.objects import OD, FunctionCode, NmtState, OperationMode, emcy_text
from motor_driver.diagnostics.health import ERROR, OK, STALE, WARN, drive_health
from motor_driver.drive.received.position import PositionFilter
from motor_driver.drive.received.tpdo import decode_tpdo
from motor_driver.drive.values import DriveState, Received
from motor_driver.drive.verdict import DriveFacts, Verdict, judge, missing_tpdos
from motor_driver.protocol.cia402 import SW, State, decode_state
from motor_driver.protocol.pdo import TpdoLayout, plan_pdos
from motor_driver.protocol.units import Scale, scale_from_objects, unit_object_answer
from motor_driver.recording.published import joint_entry, motor_state_fields
from motor_driver.recording.ros2defs import CAN_FRAME, DIAGNOSTIC_ARRAY, DRIVE_STATUS, JOINT_STATE
from motor_driver.recording.timemerge import LIVE_HOLD_S, Frame, TimeMerge

logger = logging.getLogger(__name__)

__all__ = ["DIAGNOSTICS_TOPIC", "FRAMES_TOPIC", "FROM_DRIVER", "JOINT_STATES_TOPIC", "BusView", "Emit", "Frame", "UnitObjects", "ViewDrive",
           "drive_row", "key_of", "key_text", "status_topic", "view_drives"]

#: Where the messages go: (topic, message type, message, log time in ns).
Emit = Callable[[str, str, dict[str, Any], int], None]
#: A drive's unit objects: (index, sub) -> value, as :func:`motor_driver.protocol.units.read_unit_objects` gives them.
UnitObjects = Mapping[tuple[int, int], int]

FRAMES_TOPIC = "/can/frames"
JOINT_STATES_TOPIC = "/joint_states"
DIAGNOSTICS_TOPIC = "/diagnostics"
#: Every drive's diagnostics this often (frame time), and lost drives looked for this often.
SUMMARY_PERIOD_S = 1.0
LOST_CHECK_S = 0.1
#: Where a drive's units came from (:meth:`BusView.units`): its answers seen in the frames, a
#: recording's metadata, the driver's own boot (an incident's .mcap), the config alone.
FROM_DRIVE, FROM_RECORDING, FROM_DRIVER, FROM_CONFIG = "drive", "recording", "driver", "config"


def status_topic(drive: str) -> str:
    return f"/drives/{drive}/status"


def stamp(t: float) -> dict[str, int]:
    """A builtin_interfaces/Time of ``t`` (seconds since the epoch)."""
    ns = round(t * 1e9)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _name(enum: Any, value: int) -> str:
    try:
        return str(enum(value).name)
    except ValueError:
        return f"0x{value:02X}"


def key_text(key: tuple[int, int]) -> str:
    """``0x608F:1``: a unit object's name in a recording's metadata."""
    return f"0x{key[0]:04X}:{key[1]}"


def key_of(text: str) -> tuple[int, int]:
    index, sub = text.split(":")
    return int(index, 16), int(sub)


@dataclass
class ViewDrive:
    """One drive as the view knows it: its config, PDO layouts and units, and what its frames said
    last (the feeding thread's)."""

    config: DriveConfig
    sync_period_s: float
    layouts: dict[int, TpdoLayout]
    controlword_rpdos: frozenset[int]
    scale: Scale = field(init=False)
    positions: PositionFilter = field(init=False)
    name: str = field(init=False)  # name, bus and node id: the config's, for short
    bus: str = field(init=False)
    node_id: int = field(init=False)
    units_from: str = FROM_CONFIG
    unit_objects: dict[tuple[int, int], int] = field(default_factory=dict)  # the drive's, as answered
    rx: Received = field(default_factory=Received)
    controlword: int = 0
    nmt: str = ""
    emcy_code: int = 0
    emcy_t: float = 0.0
    last_heartbeat: float | None = None
    heartbeat_missing: bool = False  # no heartbeat within its timeout (lost)
    reset_since_operational: bool = False  # a boot-up came after its last OPERATIONAL heartbeat
    got: set[int] = field(default_factory=set)  # TPDOs of this cycle
    newest: float = 0.0  # the time of the newest of them
    sync_cobs: frozenset[int] = frozenset()
    sync_heard: dict[int, float] = field(default_factory=dict)  # each SYNC TPDO's newest time (0.0 never)

    def __post_init__(self) -> None:
        self.name, self.bus, self.node_id = self.config.name, self.config.bus, self.config.node_id
        self.sync_cobs = frozenset(c for c, layout in self.layouts.items() if set(layout.indexes) & {
            OD.POSITION_ACTUAL, OD.VELOCITY_ACTUAL, OD.TORQUE_ACTUAL})
        self.sync_heard = dict.fromkeys(sorted(self.sync_cobs), 0.0)
        self.has_torque = any(OD.TORQUE_ACTUAL in layout.indexes for layout in self.layouts.values())
        self.positions = PositionFilter(self.config.node_id, self.sync_period_s)
        self._rescale()

    def take_units(self, objects: UnitObjects, source: str) -> None:
        """The drive's unit objects (its answers seen on the bus, or a recording's metadata)."""
        self.unit_objects.update(objects)
        self.units_from = source
        self._rescale()

    def on_unit_answer(self, key: tuple[int, int], value: int | None) -> None:
        """Its SDO answer to the read of one unit object (None: it has no such object)."""
        if value is None:
            self.unit_objects.pop(key, None)
        else:
            self.unit_objects[key] = value
        self.units_from = FROM_DRIVE
        self._rescale()

    def _rescale(self) -> None:
        """The scale the driver derives from the drive's objects (none: the config's alone)."""
        cfg = self.config
        try:
            self.scale, _ = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm,
                                               dict(self.unit_objects), invert=cfg.invert, offset_deg=cfg.offset_deg)
        except UnitError as err:  # half a ratio read so far, or objects the driver refuses to boot on
            logger.debug("%s: unit objects %s not plausible (%s): the scale before stands", cfg.name,
                         self.unit_objects, err)
            if not hasattr(self, "scale"):
                self.scale, _ = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm, {},
                                                   invert=cfg.invert, offset_deg=cfg.offset_deg)
        self.positions.set_units(self.scale, cfg.max_velocity_deg_s)

    @property
    def has_position(self) -> bool:
        return any(OD.POSITION_ACTUAL in self.layouts[c].indexes for c in self.got)

    def on_tpdo(self, cob: int, data: bytes, t: float) -> None:
        layout = self.layouts[cob]
        try:
            values = layout.codec.unpack_from(data)
        except struct.error:
            return  # a short TPDO: the driver ignores it too
        sw, mode, position, velocity, torque, took = decode_tpdo(layout.indexes, values, self.rx, t, self.positions)
        rx = self.rx
        if cob in self.sync_cobs:  # the data whole as the driver judges it (Received.whole_rx)
            self.sync_heard[cob] = t
            whole = min(self.sync_heard.values())
        else:
            whole = rx.whole_rx if self.sync_cobs else t
        self.rx = Received(sw, mode, position, velocity, torque, t, t, self.positions.reference, 0.0,
                           t if took else rx.position_stamp, t if took else rx.position_rx, whole)
        self.got.add(cob)
        self.newest = max(self.newest, t)

    def facts(self, now: float) -> DriveFacts:
        """What the verdict on the drive is judged from, as its frames show it at ``now``: booted
        while it is OPERATIONAL, armed while Operation Enabled (a recording sees no command)."""
        rx, cfg = self.rx, self.config
        state = decode_state(rx.statusword)
        code = self.emcy_code
        bound = cfg.stale_after_syncs * self.sync_period_s
        return DriveFacts(
            self.name, data_age_s=now - rx.whole_rx if rx.whole_rx else math.inf, stale_after_s=bound,
            missing=missing_tpdos(self.sync_heard, self.layouts, now=now, bound=bound),
            heartbeat_age_s=now - self.last_heartbeat if self.last_heartbeat is not None else math.inf,
            nmt=self.nmt or "UNKNOWN", state=state, lost=self.heartbeat_missing,
            booted=self.nmt == NmtState.OPERATIONAL.name or (not self.nmt and bool(rx.rx_monotonic)),
            rebooting=self.reset_since_operational, armed=state == State.OPERATION_ENABLED, emcy_code=code,
            emcy_text=emcy_text(code) if code else "", emcy_stamp=self.emcy_t)

    def state(self, now: float) -> tuple[DriveState, Verdict]:
        """The drive as the driver's snapshot would show it at ``now``, and the verdict on it."""
        facts = self.facts(now)
        verdict = judge(facts)
        rx, scale = self.rx, self.scale
        code = self.emcy_code
        return DriveState(
            name=self.name, node_id=self.node_id, angle_deg=scale.counts_to_deg(rx.position_counts),
            velocity_deg_s=scale.counts_s_to_deg_s(rx.velocity_counts_s),
            torque_nm=scale.permille_to_nm(rx.torque_permille) if self.has_torque else math.nan,
            statusword=rx.statusword, state=facts.state, mode=rx.mode, nmt=facts.nmt, error_code=code,
            error_text=emcy_text(code) if code else "", stamp=rx.stamp, heartbeat_age_s=facts.heartbeat_age_s,
            target_reached=bool(rx.statusword & SW.TARGET_REACHED), data_age_s=facts.data_age_s,
            reference=rx.reference, whole_rx=rx.whole_rx, judged=(facts, verdict)), verdict


def view_drives(config: RoverConfig, units: Mapping[str, UnitObjects] | None = None,
                source: str = FROM_RECORDING) -> list[ViewDrive]:
    """The config's drives, each with the PDO map the driver gives it and its units: ``units``
    (drive name -> unit objects, from ``source``: a recording's metadata, the driver) where given,
    else the config's until the drive's answers to a boot's reads of them are seen."""
    drives = []
    for d in config.drives:
        plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
        drive = ViewDrive(d, config.bus(d.bus).sync_period_s, {p.cob_id: TpdoLayout.from_map(p) for p in plan.tpdos},
                          frozenset(p.cob_id for p in plan.rpdos if p.indexes[:1] == (OD.CONTROLWORD,)))
        if units and d.name in units:
            drive.take_units(units[d.name], source)
        drives.append(drive)
    return drives


def drive_row(state: DriveState, verdict: Verdict, config: DriveConfig) -> tuple[int, str, dict[str, object]]:
    """A drive's /diagnostics level, message and values, by the live /diagnostics' rules
    (:func:`motor_driver.diagnostics.health.drive_health`), with the verdict on it."""
    health = drive_health(state, heartbeat_period_s=config.heartbeat_period_s)
    return health.level, health.message, {**health.values, "verdict": verdict.text()}


class BusView:
    """Frames in, ROS 2 messages out (see the module's docstring). ``frames=False`` leaves the
    raw frames out (the drives only); ``hold_s``: how long frame time waits for a quiet bus
    (:class:`~motor_driver.recording.timemerge.TimeMerge`)."""

    def __init__(self, drives: Iterable[ViewDrive], emit: Emit, *, frames: bool = True,
                 hold_s: float = LIVE_HOLD_S) -> None:
        self.drives = list(drives)
        self._emit = emit
        self._frames = frames
        self._merge = TimeMerge(hold_s, dict.fromkeys(d.bus for d in self.drives))
        self._routes: dict[tuple[str, int], tuple[str, ViewDrive]] = {}
        for d in self.drives:
            self._routes.update({(d.bus, cob): ("tpdo", d) for cob in d.layouts})
            self._routes.update({(d.bus, cob): ("rpdo", d) for cob in d.controlword_rpdos})
            self._routes[(d.bus, FunctionCode.EMCY + d.node_id)] = ("emcy", d)
            self._routes[(d.bus, FunctionCode.HEARTBEAT + d.node_id)] = ("heartbeat", d)
            self._routes[(d.bus, FunctionCode.SDO_TX + d.node_id)] = ("sdo", d)
        self._expected: set[str] = set()  # the drives of the last cycle
        self._next_check = -math.inf
        self._next_summary = -math.inf
        self._now = 0.0

    def channels(self) -> list[tuple[str, str]]:
        """Every (topic, type) this view may send, for a live view to advertise before any frame."""
        topics = [(FRAMES_TOPIC, CAN_FRAME)] if self._frames else []
        if self.drives:
            topics += [(JOINT_STATES_TOPIC, JOINT_STATE), (DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY)]
            topics += [(status_topic(d.name), DRIVE_STATUS) for d in self.drives]
        return topics

    def units(self) -> dict[str, dict[str, Any]]:
        """Each drive's units as the view decodes them: where from (``drive``: its answers to a
        boot's reads seen in the frames; ``recording``: a recording's metadata; ``config``: none
        seen, the config's alone), the unit objects and the scale derived."""
        return {d.name: {"from": d.units_from, "objects": {key_text(k): v for k, v in sorted(d.unit_objects.items())},
                         "counts_per_deg": d.scale.counts_per_deg,
                         "velocity_units_per_deg_s": d.scale.velocity_units_per_deg_s or d.scale.counts_per_deg,
                         "rated_torque_nm": d.scale.rated_torque_nm, "gear_ratio": d.scale.gear_ratio}
                for d in self.drives}

    def config_units(self) -> list[str]:
        """The drives decoded in the config's units alone (no unit object of theirs seen or given)."""
        return [d.name for d in self.drives if d.units_from == FROM_CONFIG]

    def feed(self, frame: Frame) -> None:
        """One frame of any bus, in the order it was read."""
        for each in self._merge.push(frame):
            self._take(each)

    def _take(self, frame: Frame) -> None:
        t, bus, cob, extended, remote, error, dlc, data = frame
        self._now = max(self._now, t)
        if self._frames:
            self._emit(FRAMES_TOPIC, CAN_FRAME, {
                "header": {"stamp": stamp(t), "frame_id": bus}, "id": cob, "is_extended": extended, "is_rtr": remote,
                "is_error": error, "dlc": dlc, "data": data}, round(t * 1e9))
        if t >= self._next_check and self.drives:
            self._next_check = t + LOST_CHECK_S
            self._look_for_lost(t)
        route = None if extended or error or remote else self._routes.get((bus, cob))
        if route is None:
            return
        kind, drive = route
        if kind == "tpdo":
            if cob in drive.got and cob in drive.sync_cobs:
                self.flush()  # its second of a cycle: the cycle is over
            drive.on_tpdo(cob, data, t)
            if self._cycle_complete():
                self.flush()
        elif kind == "rpdo" and len(data) >= 2:
            drive.controlword = int.from_bytes(data[:2], "little")
        elif kind == "emcy" and len(data) >= 3:
            self._on_emcy(drive, data, t)
        elif kind == "heartbeat" and data:
            self._on_heartbeat(drive, data[0] & 0x7F, t)
        elif kind == "sdo" and (answer := unit_object_answer(data)) is not None:
            drive.on_unit_answer(*answer)

    def incident(self, t: float, who: str, text: str, level: int = ERROR, **values: object) -> None:
        """A diagnostic from outside the frames (the flight recorder's incident)."""
        self._diagnose(t, [(level, who, text, values)])

    def finish(self) -> None:
        """Every frame held, and the cycle in hand, out (the end of a recording)."""
        for frame in self._merge.flush():
            self._take(frame)
        self.flush()

    # ------------------------------------------------------------------ cycles
    def _cycle_complete(self) -> bool:
        live = [d for d in self.drives if d.name in self._expected or d.got]
        return bool(live) and all(d.sync_cobs <= d.got for d in live)

    def flush(self) -> None:
        cycle = [d for d in self.drives if d.got]
        if not cycle:
            return
        newest = max(d.newest for d in cycle)
        states = {d.name: d.state(newest) for d in self.drives}
        if any(d.has_position for d in cycle):
            self._joint_states(newest, [states[d.name][0] for d in self.drives])
        for d in cycle:
            self._emit(status_topic(d.name), DRIVE_STATUS, self._status(d, states[d.name][0]), round(d.newest * 1e9))
        self._expected = {d.name for d in cycle}
        for d in cycle:
            d.got = set()
        if newest >= self._next_summary:
            self._next_summary = newest + SUMMARY_PERIOD_S
            self._summary(newest, states)

    def _joint_states(self, newest: float, states: list[DriveState]) -> None:
        """Every drive of the config, in its order, as the driver publishes them
        (:func:`motor_driver.recording.published.joint_entry`): NaN only while stale or never heard."""
        entries = [joint_entry(s) for s in states]
        self._emit(JOINT_STATES_TOPIC, JOINT_STATE, {
            "header": {"stamp": stamp(newest), "frame_id": ""}, "name": [s.name for s in states],
            "position": [e[0] for e in entries], "velocity": [e[1] for e in entries],
            "effort": [e[2] for e in entries]}, round(newest * 1e9))

    def _status(self, d: ViewDrive, state: DriveState) -> dict[str, Any]:
        fields = motor_state_fields(state, d.config.is_continuous)._asdict()
        motor = {"header": {"stamp": stamp(fields.pop("stamp")), "frame_id": d.name}, **fields}
        return {"motor": motor, "bus": d.bus, "node_id": d.node_id, "statusword": state.statusword,
                "controlword": d.controlword, "mode": state.mode, "mode_name": _name(OperationMode, state.mode),
                "nmt": d.nmt, "emcy_code": d.emcy_code, "emcy_text": emcy_text(d.emcy_code) if d.emcy_code else ""}

    # ------------------------------------------------------------------ what the recorder watches
    def _on_emcy(self, d: ViewDrive, data: bytes, t: float) -> None:
        code, register = int.from_bytes(data[:2], "little"), data[2]
        d.emcy_code, d.emcy_t = code, t
        text = f"EMCY 0x{code:04X} {emcy_text(code)}" if code else "EMCY error reset"
        self._diagnose(t, [(ERROR if code else OK, d.name, text, {"error_register": f"0x{register:02X}"})])

    def _on_heartbeat(self, d: ViewDrive, state: int, t: float) -> None:
        d.last_heartbeat = t if d.last_heartbeat is None else max(d.last_heartbeat, t)
        d.nmt = _name(NmtState, state)
        if state == NmtState.BOOTUP:
            d.reset_since_operational = True
            self._diagnose(t, [(WARN, d.name, "boot-up: the drive reset or was power-cycled", {})])
            return
        if state == NmtState.OPERATIONAL:
            d.reset_since_operational = False
        if d.heartbeat_missing:
            d.heartbeat_missing = False
            self._diagnose(t, [(OK, d.name, f"heartbeat back ({d.nmt})", {})])

    def _look_for_lost(self, t: float) -> None:
        for d in self.drives:
            if not d.heartbeat_missing and d.last_heartbeat is not None and t - d.last_heartbeat > d.config.heartbeat_timeout_s:
                d.heartbeat_missing = True
                self._expected.discard(d.name)
                self._diagnose(t, [(ERROR, d.name, f"heartbeat lost: none for {t - d.last_heartbeat:.2f} s (timeout"
                                                   f" {d.config.heartbeat_timeout_s:g} s)", {})])

    def _summary(self, t: float, states: Mapping[str, tuple[DriveState, Verdict]]) -> None:
        rows: list[tuple[int, str, str, dict[str, object]]] = []
        for d in self.drives:
            state, verdict = states[d.name]
            if d.last_heartbeat is None and not d.rx.rx_monotonic:
                rows.append((STALE, d.name, "not heard in this recording", {}))
                continue
            level, text, values = drive_row(state, verdict, d.config)
            rows.append((level, d.name, text, values))
        self._diagnose(t, rows)

    def _diagnose(self, t: float, rows: list[tuple[int, str, str, dict[str, object]]]) -> None:
        if not self.drives:
            return
        node = {d.name: d for d in self.drives}
        status = [{"level": level, "name": f"rovercan: {who}", "message": text,
                   "hardware_id": f"{node[who].bus} node {node[who].node_id}" if who in node else who,
                   "values": [{"key": k, "value": str(v)} for k, v in values.items()]}
                  for level, who, text, values in rows]
        self._emit(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, {"header": {"stamp": stamp(t), "frame_id": ""},
                                                          "status": status}, round(t * 1e9))

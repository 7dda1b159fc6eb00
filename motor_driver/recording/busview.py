"""The bus as ROS 2 messages (pure, no rclpy): every frame, and with a config every drive decoded
by its EDS and the driver's PDO map, for MCAP files and the live Foxglove view.

:class:`BusView` takes frames (:data:`Frame`, time-ordered) and hands out messages as plain dicts
(``emit(topic, type, message, time_ns)``, types from :mod:`motor_driver.recording.ros2defs`):

- ``/can/frames`` (rovercan_msgs/CanFrame): each frame, its bus, id, flags, data and time;
- ``/joint_states`` (sensor_msgs/JointState): the drives' angle (rad), velocity (rad/s) and
  torque (Nm) of one SYNC cycle, stamped with the newest frame of it. A cycle ends when every
  drive heard in the last one has sent each of its SYNC TPDOs, or when one sends a second. It
  names every drive of the config, always in its order; the values of one whose TPDOs did not
  come in the cycle (silent, stale or lost) are NaN: absent, never its last values again;
- ``/drives/<name>/status`` (rovercan_msgs/DriveStatus): a drive's CiA 402 state, statusword,
  controlword, mode, NMT state and EMCY, for each cycle its TPDOs came in (none otherwise);
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): what the flight recorder watches for (an
  EMCY, a boot-up, a heartbeat lost and back) when it is seen, and every drive once a second.

The PDO layouts are the driver's own (:func:`motor_driver.protocol.pdo.plan_pdos`, decoded with its
:class:`~motor_driver.protocol.pdo.TpdoLayout`), the units its :class:`~motor_driver.protocol.units.Scale` from the
config, the states :func:`motor_driver.protocol.cia402.decode_state`. Owner: the one thread that feeds it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from can_config.eds import load_drive_od
from can_config.model import RoverConfig
from can_config.objects import OD, FunctionCode, NmtState, OperationMode, emcy_text
from motor_driver.protocol.cia402 import FAULT_STATES, State, decode_state
from motor_driver.protocol.pdo import TpdoLayout, plan_pdos
from motor_driver.protocol.units import Scale
from motor_driver.recording.ros2defs import CAN_FRAME, DIAGNOSTIC_ARRAY, DRIVE_STATUS, JOINT_STATE

#: One frame: time.time(), bus name, COB-ID, extended, remote, error frame, DLC, data.
Frame = tuple[float, str, int, bool, bool, bool, int, bytes]
#: Where the messages go: (topic, message type, message, log time in ns).
Emit = Callable[[str, str, dict[str, Any], int], None]

FRAMES_TOPIC = "/can/frames"
JOINT_STATES_TOPIC = "/joint_states"
DIAGNOSTICS_TOPIC = "/diagnostics"
#: Every drive's diagnostics this often (frame time), and lost drives looked for this often.
SUMMARY_PERIOD_S = 1.0
LOST_CHECK_S = 0.1
OK, WARN, ERROR, STALE = 0, 1, 2, 3


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


@dataclass
class ViewDrive:
    """One drive as the view knows it: its identity, PDO layouts and units (from the config), and
    what its frames said last (the feeding thread's)."""

    name: str
    bus: str
    node_id: int
    scale: Scale
    layouts: dict[int, TpdoLayout]
    controlword_rpdos: frozenset[int]
    heartbeat_timeout_s: float
    sync_cobs: frozenset[int] = frozenset()
    statusword: int = 0
    controlword: int = 0
    mode: int = 0
    position_counts: int = 0
    velocity_counts_s: int = 0
    torque_permille: int | None = None
    nmt: str = ""
    emcy_code: int = 0
    last_heartbeat: float | None = None
    heartbeat_missing: bool = False  # no heartbeat within its timeout (lost)
    got: set[int] = field(default_factory=set)  # TPDOs of this cycle
    newest: float = 0.0  # the time of the newest of them

    def __post_init__(self) -> None:
        self.sync_cobs = frozenset(c for c, layout in self.layouts.items() if set(layout.indexes) & {
            OD.POSITION_ACTUAL, OD.VELOCITY_ACTUAL, OD.TORQUE_ACTUAL})

    @property
    def has_position(self) -> bool:
        return any(OD.POSITION_ACTUAL in self.layouts[c].indexes for c in self.got)

    def on_tpdo(self, cob: int, data: bytes, t: float) -> None:
        layout = self.layouts[cob]
        if len(data) < layout.codec.size:
            return  # a short TPDO: the driver ignores it too
        for index, value in zip(layout.indexes, layout.codec.unpack_from(data), strict=True):
            if index == OD.STATUSWORD:
                self.statusword = value
            elif index == OD.POSITION_ACTUAL:
                self.position_counts = value
            elif index == OD.VELOCITY_ACTUAL:
                self.velocity_counts_s = value
            elif index == OD.TORQUE_ACTUAL:
                self.torque_permille = value
            elif index == OD.MODES_OF_OPERATION_DISPLAY:
                self.mode = value
        self.got.add(cob)
        self.newest = max(self.newest, t)


def view_drives(config: RoverConfig) -> list[ViewDrive]:
    """The config's drives, each with the PDO map the driver gives it and its units."""
    drives = []
    for d in config.drives:
        plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
        scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
        drives.append(ViewDrive(d.name, d.bus, d.node_id, scale, {p.cob_id: TpdoLayout.from_map(p) for p in plan.tpdos},
                                frozenset(p.cob_id for p in plan.rpdos if p.indexes[:1] == (OD.CONTROLWORD,)),
                                d.heartbeat_timeout_s))
    return drives


class BusView:
    """Frames in, ROS 2 messages out (see the module's docstring). ``frames=False`` leaves the
    raw frames out (the drives only)."""

    def __init__(self, drives: Iterable[ViewDrive], emit: Emit, *, frames: bool = True) -> None:
        self.drives = list(drives)
        self._emit = emit
        self._frames = frames
        self._routes: dict[tuple[str, int], tuple[str, ViewDrive]] = {}
        for d in self.drives:
            self._routes.update({(d.bus, cob): ("tpdo", d) for cob in d.layouts})
            self._routes.update({(d.bus, cob): ("rpdo", d) for cob in d.controlword_rpdos})
            self._routes[(d.bus, FunctionCode.EMCY + d.node_id)] = ("emcy", d)
            self._routes[(d.bus, FunctionCode.HEARTBEAT + d.node_id)] = ("heartbeat", d)
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

    def feed(self, frame: Frame) -> None:
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

    def incident(self, t: float, who: str, text: str, level: int = ERROR, **values: object) -> None:
        """A diagnostic from outside the frames (the flight recorder's incident)."""
        self._diagnose(t, [(level, who, text, values)])

    def finish(self) -> None:
        """The cycle in hand, out (the end of a recording)."""
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
        if any(d.has_position for d in cycle):
            self._joint_states(newest)
        for d in cycle:
            self._emit(status_topic(d.name), DRIVE_STATUS, self._status(d), round(d.newest * 1e9))
        self._expected = {d.name for d in cycle}
        for d in cycle:
            d.got = set()
        if newest >= self._next_summary:
            self._next_summary = newest + SUMMARY_PERIOD_S
            self._summary(newest)

    def _joint_states(self, newest: float) -> None:
        """Every drive of the config, in its order; one whose TPDOs did not come in this cycle
        (silent, stale, lost) is NaN: absent, never its last value again."""
        named = self.drives
        nan = math.nan
        self._emit(JOINT_STATES_TOPIC, JOINT_STATE, {
            "header": {"stamp": stamp(newest), "frame_id": ""}, "name": [d.name for d in named],
            "position": [math.radians(d.scale.counts_to_deg(d.position_counts)) if d.has_position else nan for d in named],
            "velocity": [math.radians(d.scale.counts_s_to_deg_s(d.velocity_counts_s)) if d.has_position else nan for d in named],
            "effort": [self._torque_nm(d) for d in named]}, round(newest * 1e9))

    @staticmethod
    def _torque_nm(d: ViewDrive) -> float:
        fresh = d.torque_permille is not None and any(OD.TORQUE_ACTUAL in d.layouts[c].indexes for c in d.got)
        return d.scale.permille_to_nm(d.torque_permille) if fresh and d.torque_permille is not None else math.nan

    def _status(self, d: ViewDrive) -> dict[str, Any]:
        state = decode_state(d.statusword)
        fresh = d.has_position
        motor = {
            "header": {"stamp": stamp(d.newest), "frame_id": d.bus}, "name": d.name,
            "angle": d.scale.counts_to_deg(d.position_counts) if fresh else math.nan,
            "velocity": d.scale.counts_s_to_deg_s(d.velocity_counts_s) if fresh else math.nan,
            "torque": self._torque_nm(d), "state": state.name, "enabled": state == State.OPERATION_ENABLED,
            "fault": state in FAULT_STATES, "error_code": d.emcy_code, "stale": False, "data_age": 0.0}
        return {"motor": motor, "bus": d.bus, "node_id": d.node_id, "statusword": d.statusword,
                "controlword": d.controlword, "mode": d.mode, "mode_name": _name(OperationMode, d.mode), "nmt": d.nmt,
                "emcy_code": d.emcy_code, "emcy_text": emcy_text(d.emcy_code) if d.emcy_code else ""}

    # ------------------------------------------------------------------ what the recorder watches
    def _on_emcy(self, d: ViewDrive, data: bytes, t: float) -> None:
        code, register = int.from_bytes(data[:2], "little"), data[2]
        d.emcy_code = code
        text = f"EMCY 0x{code:04X} {emcy_text(code)}" if code else "EMCY error reset"
        self._diagnose(t, [(ERROR if code else OK, d.name, text, {"error_register": f"0x{register:02X}"})])

    def _on_heartbeat(self, d: ViewDrive, state: int, t: float) -> None:
        d.last_heartbeat = t
        d.nmt = _name(NmtState, state)
        if state == NmtState.BOOTUP:
            self._diagnose(t, [(WARN, d.name, "boot-up: the drive reset or was power-cycled", {})])
        elif d.heartbeat_missing:
            d.heartbeat_missing = False
            self._diagnose(t, [(OK, d.name, f"heartbeat back ({d.nmt})", {})])

    def _look_for_lost(self, t: float) -> None:
        for d in self.drives:
            if not d.heartbeat_missing and d.last_heartbeat is not None and t - d.last_heartbeat > d.heartbeat_timeout_s:
                d.heartbeat_missing = True
                self._expected.discard(d.name)
                self._diagnose(t, [(ERROR, d.name, f"heartbeat lost: none for {t - d.last_heartbeat:.2f} s (timeout"
                                                   f" {d.heartbeat_timeout_s:g} s)", {})])

    def _summary(self, t: float) -> None:
        rows: list[tuple[int, str, str, dict[str, object]]] = []
        for d in self.drives:
            state = decode_state(d.statusword)
            level = STALE if d.last_heartbeat is None and not d.statusword else ERROR if d.heartbeat_missing or state in FAULT_STATES \
                else OK
            text = "lost" if d.heartbeat_missing else f"{state.name}, NMT {d.nmt or '?'}" + (
                f", EMCY 0x{d.emcy_code:04X} {emcy_text(d.emcy_code)}" if d.emcy_code else "")
            rows.append((level, d.name, text, {"statusword": f"0x{d.statusword:04X}", "mode": _name(OperationMode, d.mode)}))
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

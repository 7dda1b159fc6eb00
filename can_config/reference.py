"""The configuration reference of docs/configuration.md, generated from the config's own field
definitions (type, default, range, choices) and the descriptions below: one table per section.
``python -m can_config.reference`` prints it; tests/test_config_docs.py checks that the manual
holds exactly this and that every field has a description."""

from __future__ import annotations

import sys
from typing import Any

from can_config.fields import (
    BUS_FIELDS,
    DRIVE_FIELDS,
    DRIVE_SYSTEM_FIELDS,
    IDENTITY_FIELDS,
    RECORDER_FIELDS,
    REQUIRED,
    SDO_FIELDS,
    SIM_FIELDS,
    Field,
)

#: (section heading, YAML path, fields, {key: (unit, what it is)})
SECTIONS: list[tuple[str, str, dict[str, Field], dict[str, tuple[str, str]]]] = [
    ("Buses", "buses[]", BUS_FIELDS, {
        "name": ("", "the bus's name, used by drives' `bus` and in logs"),
        "interface": ("", "python-can interface: `socketcan` (the rover, vcan), `socketcand` (the simulator), `pcan`, ..."),
        "channel": ("", "python-can channel: `can0`, `vcan0`, `PCAN_USBBUS1`, ..."),
        "bitrate": ("bit/s", "the bus bitrate (bus load planning; set on the interface by `can-up`)"),
        "kwargs": ("", "more python-can arguments, e.g. `{host: 127.0.0.1, port: 29536}` for socketcand"),
        "sync_period_ms": ("ms", "SYNC period: the rate of every synchronous PDO"),
        "host_node_id": ("", "the driver's own NMT id; no drive on the bus may use it"),
        "host_heartbeat_ms": ("ms", "period of the driver's heartbeat, which the drives watch"),
        "connect_timeout_ms": ("ms", "how long the driver waits for a bus server that is not there yet"),
        "sync_timer": ("", "`auto`: the daemon's or kernel's timer sends the SYNC; `thread`: a thread of the driver"),
    }),
    ("Drives", "drives[]", DRIVE_FIELDS, {
        "name": ("", "the joint's name (topics, services, /joint_states)"),
        "namespace": ("", "ROS namespace of the joint's topics"),
        "node_id": ("", "CANopen node id of the drive"),
        "bus": ("", "the bus it is on (default: the only bus)"),
        "eds": ("", "`generic` (the project's CiA 402 EDS) or the vendor's EDS, relative to the config"),
        "counts_per_rev": ("counts", "position resolution per motor turn; read from the drive's 0x608F where it has one"),
        "gear_ratio": ("", "motor turns per joint turn"),
        "rated_torque_nm": ("Nm", "the motor's rated torque (0x6076 where the drive has it): the unit of torque objects"),
        "max_torque_nm": ("Nm", "torque command limit at the joint (default: rated torque x gear ratio)"),
        "joint": ("", "`continuous` (a wheel) or `limited` (needs `min_deg`/`max_deg`)"),
        "min_deg": ("deg", "lower position limit of a limited joint (also written to the drive, 0x607D)"),
        "max_deg": ("deg", "upper position limit of a limited joint"),
        "max_velocity_deg_s": ("deg/s", "velocity command limit, every path (API, CLI, ROS)"),
        "profile_velocity_deg_s": ("deg/s", "profile position speed (0x6081)"),
        "profile_acceleration_deg_s2": ("deg/s^2", "profile acceleration and deceleration (0x6083/0x6084)"),
        "heartbeat_period_ms": ("ms", "the drive's heartbeat period (0x1017), or the guard time when node-guarded"),
        "heartbeat_timeout_ms": ("ms", "no heartbeat (or guard answer) for this long: the drive is lost"),
        "watchdog_ms": ("ms", "no velocity/torque command for this long: the driver stops the joint"),
        "arm_on_start": ("", "enable the drive when the driver starts (off: safe by default)"),
        "restore_enable_after_reboot": ("", "enable again after the drive rebooted by itself (off by default)"),
        "homing_method": ("", "CiA 402 homing method (0x6098)"),
        "homing_speed_deg_s": ("deg/s", "homing speed (0x6099)"),
        "homing_timeout_s": ("s", "homing gives up after this long"),
        "identity": ("", "expected 0x1018 (`vendor_id`, `product_code`, `revision`); default: the EDS's"),
        "invert": ("", "the joint turns the other way than the motor (a mirrored wheel)"),
        "offset_deg": ("deg", "the joint angle at drive position 0"),
        "quick_stop_deceleration_deg_s2": ("deg/s^2", "quick-stop deceleration (0x6085; default 4x the profile's)"),
        "host_timeout_ms": ("ms", "the drive stops itself when the host is silent this long (default 3x the host heartbeat)"),
        "on_host_loss": ("", "what the drive does then (0x6007): `quick_stop`, `disable` or `fault`"),
        "allow_no_host_watch": ("", "arm a drive that cannot watch the host (loud warning): NOTHING stops it if the host dies"),
        "host_watch": ("", "`auto` (heartbeat consumer where the drive has 0x1016, else node guarding), `heartbeat`, `guarding`"),
        "stale_after_syncs": ("SYNC periods", "no PDO for this many SYNC periods: the drive's data are reported stale"),
        "sdo_timeout_ms": ("ms", "one SDO answer (a whole read: 4x this at most)"),
        "boot_timeout_ms": ("ms", "from NMT reset to the drive's boot-up"),
        "sdo": ("", "vendor parameters written at boot, in order (table below)"),
        "velocity_mode": ("", "how /joint_commands velocities are sent: `profile` (PV) or `cyclic` (CSV)"),
        "torque_mode": ("", "how efforts are sent: `profile` (PT) or `cyclic` (CST)"),
        "sim": ("", "the simulator's model of this drive (table below)"),
    }),
    ("A drive's identity", "drives[].identity", IDENTITY_FIELDS, {
        "vendor_id": ("", "0x1018:1, compared at boot"),
        "product_code": ("", "0x1018:2"),
        "revision": ("", "0x1018:3"),
    }),
    ("A drive's vendor parameters", "drives[].sdo[]", SDO_FIELDS, {
        "index": ("", "object index"),
        "sub": ("", "sub-index"),
        "value": ("", "the value written"),
        "check": ("", "read it back after writing"),
        "size": ("bytes", "the object's width where the EDS does not list it"),
    }),
    ("A drive's simulated motor", "drives[].sim", SIM_FIELDS, {
        "inertia_kg_m2": ("kg m^2", "rotor plus load inertia"),
        "viscous_nm_s_rad": ("Nm s/rad", "viscous friction"),
        "coulomb_nm": ("Nm", "Coulomb friction"),
        "load_nm": ("Nm", "a constant load torque"),
        "torque_lag_ms": ("ms", "current loop time constant"),
        "bandwidth_hz": ("Hz", "velocity loop bandwidth (gains derived from it)"),
        "position_kp": ("1/s", "position gain (default: from the bandwidth)"),
        "velocity_kp": ("Nm s/rad", "velocity gain (default: from the bandwidth)"),
        "velocity_ki": ("Nm/rad", "velocity integral gain (default: from the bandwidth)"),
        "velocity_ff": ("", "velocity feed-forward"),
    }),
    ("The drive system (/cmd_vel)", "drive_system", DRIVE_SYSTEM_FIELDS, {
        "left": ("", "the drives of the left side"),
        "right": ("", "the drives of the right side"),
        "track_width_m": ("m", "distance between the left and right wheels"),
        "wheel_radius_m": ("m", "wheel radius"),
        "cmd_timeout_ms": ("ms", "no /cmd_vel for this long: the wheels ramp down and stop"),
        "max_accel_m_s2": ("m/s^2", "acceleration limit of the body and every wheel"),
        "max_speed_m_s": ("m/s", "body speed and every wheel's rim speed"),
        "max_angular_rad_s": ("rad/s", "turn rate; a faster /cmd_vel is scaled down as a whole"),
    }),
    ("The flight recorder", "recorder", RECORDER_FIELDS, {
        "enabled": ("", "keep the ring and write incidents"),
        "dir": ("", "where incidents go (default `$ROVERCAN_INCIDENT_DIR`, else `~/.local/state/rovercan/incidents`)"),
        "seconds": ("s", "the ring: frames and states kept before an incident"),
        "after_s": ("s", "kept after the incident"),
        "max_mb": ("MB", "the directory's cap; the oldest incidents go first"),
        "plot": ("", "draw a PNG of each incident (needs matplotlib)"),
    }),
]
BEGIN = "<!-- reference: generated by python -m can_config.reference; do not edit by hand -->"
END = "<!-- end of reference -->"


def _num(value: float) -> str:
    return f"{int(value):,}" if float(value).is_integer() and abs(value) < 1e15 else f"{value:g}"


def _default(field: Field) -> str:
    if field.default is REQUIRED:
        return "required"
    value: Any = field.default
    if value is None:
        return "-"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return _num(value)
    if value in ({}, []):
        return "none"
    return f"`{value}`" if value != "" else '`""`'


def _allowed(field: Field) -> str:
    if field.choices:
        return " / ".join(f"`{c}`" for c in field.choices)
    if field.low is not None and field.high is not None:
        return f"{'over ' if field.low_open else ''}{_num(field.low)} to {_num(field.high)}"
    return {"bool": "true / false", "map": "mapping", "list": "list", "list_names": "list of drive names",
            "path": "path or `generic`", "name": "a name", "namespace": "a ROS namespace", "str": "text",
            "number": "a number"}.get(field.kind, field.kind)


def missing_descriptions() -> list[str]:
    return [f"{path}.{key}" for _, path, fields, text in SECTIONS for key in fields if key not in text] + \
        [f"{path}.{key} (no such field)" for _, path, fields, text in SECTIONS for key in text if key not in fields]


def reference() -> str:
    out = [BEGIN]
    for heading, path, fields, text in SECTIONS:
        out += ["", f"### {heading} (`{path}`)", "", "| key | unit | default | allowed | what it is |",
                "|---|---|---|---|---|"]
        for key, field in fields.items():
            unit, what = text.get(key, ("", ""))
            out.append(f"| `{key}` | {unit} | {_default(field)} | {_allowed(field)} | {what} |")
    out += ["", END]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference())

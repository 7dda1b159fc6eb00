"""The configuration's keys: per section, each YAML key's kind, default, range and choices, and
the checks that turn a YAML value into a typed one with an error that names the key. The
reference in docs/configuration.md is generated from these (:mod:`can_config.reference`).
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.model import GEAR_RATIO_MAX, GEAR_RATIO_MIN, ON_HOST_LOSS

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
REQUIRED: Any = object()


@dataclass(frozen=True)
class Field:
    kind: str  # "int", "float", "bool", "str", "name", "namespace", "path", "map", "list", "list_names",
    #            "opt_float", "opt_int" (a byte size), "number" (int or float)
    default: Any = REQUIRED
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    low_open: bool = False


BUS_FIELDS: dict[str, Field] = {
    "name": Field("name"),
    "interface": Field("str"),
    "channel": Field("str"),
    "bitrate": Field("int", 1_000_000, 10_000, 8_000_000),
    "kwargs": Field("map", {}),
    "sync_period_ms": Field("float", 10.0, 1.0, 1000.0),
    "host_node_id": Field("int", 127, 1, 127),
    "host_heartbeat_ms": Field("float", 50.0, 10.0, 1000.0),
    "connect_timeout_ms": Field("float", 10_000.0, 0.0, 600_000.0),
    "sync_timer": Field("str", "auto", choices=("auto", "thread")),
}
IDENTITY_FIELDS: dict[str, Field] = {
    "vendor_id": Field("int", None, 0, 0xFFFF_FFFF),
    "product_code": Field("int", None, 0, 0xFFFF_FFFF),
    "revision": Field("int", None, 0, 0xFFFF_FFFF),
}
DRIVE_FIELDS: dict[str, Field] = {
    "name": Field("name"),
    "namespace": Field("namespace", ""),
    "node_id": Field("int", REQUIRED, 1, 127),
    "bus": Field("str", None),
    "eds": Field("path", "generic"),
    "counts_per_rev": Field("int", None, 1, 2**31 - 1),
    "gear_ratio": Field("float", 1.0, GEAR_RATIO_MIN, GEAR_RATIO_MAX),
    "rated_torque_nm": Field("float", 1.0, 0.0, 1e5, low_open=True),
    "max_torque_nm": Field("opt_float", None, 0.0, 1e6, low_open=True),
    "joint": Field("str", "continuous", choices=("continuous", "limited")),
    "min_deg": Field("opt_float", None, -1e7, 1e7),
    "max_deg": Field("opt_float", None, -1e7, 1e7),
    "max_velocity_deg_s": Field("float", 360.0, 0.0, 1e6, low_open=True),
    "profile_velocity_deg_s": Field("float", 90.0, 0.0, 1e6, low_open=True),
    "profile_acceleration_deg_s2": Field("float", 360.0, 0.0, 1e7, low_open=True),
    "heartbeat_period_ms": Field("float", 100.0, 10.0, 10_000.0),
    "heartbeat_timeout_ms": Field("float", 350.0, 20.0, 60_000.0),
    "watchdog_ms": Field("float", 500.0, 10.0, 60_000.0),
    "arm_on_start": Field("bool", False),
    "restore_enable_after_reboot": Field("bool", False),
    "homing_method": Field("int", 35, -128, 127),
    "homing_speed_deg_s": Field("float", 30.0, 0.0, 1e6, low_open=True),
    "homing_timeout_s": Field("float", 10.0, 0.1, 600.0),
    "identity": Field("map", {}),
    "invert": Field("bool", False),
    "offset_deg": Field("float", 0.0, -1e6, 1e6),
    "quick_stop_deceleration_deg_s2": Field("opt_float", None, 0.0, 1e7, low_open=True),
    "host_timeout_ms": Field("opt_float", None, 20.0, 65_535.0),
    "on_host_loss": Field("str", "quick_stop", choices=tuple(ON_HOST_LOSS)),
    "allow_no_host_watch": Field("bool", False),
    "host_watch": Field("str", "auto", choices=("auto", "heartbeat", "guarding")),
    "stale_after_syncs": Field("int", 5, 2, 1000),
    "sdo_timeout_ms": Field("float", 500.0, 10.0, 10_000.0),
    "boot_timeout_ms": Field("float", 2000.0, 100.0, 60_000.0),
    "sdo": Field("list", []),
    "velocity_mode": Field("str", "profile", choices=("profile", "cyclic")),
    "torque_mode": Field("str", "profile", choices=("profile", "cyclic")),
    "sim": Field("map", {}),
}
SIM_FIELDS: dict[str, Field] = {
    "inertia_kg_m2": Field("float", 1e-4, 0.0, 100.0, low_open=True),
    "viscous_nm_s_rad": Field("float", 2e-5, 0.0, 100.0),
    "coulomb_nm": Field("float", 0.03, 0.0, 1e4),
    "load_nm": Field("float", 0.0, -1e4, 1e4),
    "torque_lag_ms": Field("float", 1.0, 0.0, 100.0),
    "bandwidth_hz": Field("float", 50.0, 0.0, 1000.0, low_open=True),
    "position_kp": Field("opt_float", None, 0.0, 1e4),
    "velocity_kp": Field("opt_float", None, 0.0, 1e4),
    "velocity_ki": Field("opt_float", None, 0.0, 1e6),
    "velocity_ff": Field("float", 1.0, 0.0, 2.0),
}
SDO_FIELDS: dict[str, Field] = {
    "index": Field("int", REQUIRED, 0x1000, 0xFFFF),
    "sub": Field("int", 0, 0, 255),
    "value": Field("number", REQUIRED),
    "check": Field("bool", True),
    "size": Field("opt_int", None, 1, 8),
}
DRIVE_SYSTEM_FIELDS: dict[str, Field] = {
    "left": Field("list_names"),
    "right": Field("list_names"),
    "track_width_m": Field("float", 0.6, 0.0, 100.0, low_open=True),
    "wheel_radius_m": Field("float", 0.1, 0.0, 10.0, low_open=True),
    "cmd_timeout_ms": Field("float", 500.0, 10.0, 60_000.0),
    "max_accel_m_s2": Field("float", 1.0, 0.0, 100.0, low_open=True),
    "max_speed_m_s": Field("float", 1.0, 0.0, 100.0, low_open=True),
    "max_angular_rad_s": Field("float", 2.0, 0.0, 100.0, low_open=True),
}
RECORDER_FIELDS: dict[str, Field] = {
    "enabled": Field("bool", True),
    "dir": Field("str", None),
    "seconds": Field("float", 10.0, 1.0, 600.0),
    "after_s": Field("float", 1.0, 0.0, 60.0),
    "max_mb": Field("float", 200.0, 1.0, 1e6),
    "plot": Field("bool", True),
}
TOP_FIELDS = ("buses", "drives", "drive_system", "recorder")


class Where:
    """Formats error locations: ``file: drives[0].gear_ratio``."""

    def __init__(self, source: Path | str | None) -> None:
        self.source = str(source) if source is not None else "<config>"

    def fail(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.source}: {key}: {message}")


def check_keys(where: Where, prefix: str, data: Mapping[str, Any], known: tuple[str, ...]) -> None:
    for key in data:
        if key not in known:
            hint = difflib.get_close_matches(str(key), known, n=1)
            suggestion = f" Did you mean {hint[0]!r}?" if hint else ""
            raise where.fail(
                f"{prefix}{key}",
                f"unknown key.{suggestion} Allowed keys: {', '.join(known)}.",
            )


def convert(where: Where, key: str, value: Any, spec: Field) -> Any:
    """``value`` of ``key`` as its kind says, or a ConfigError naming the key and what is allowed."""
    if value is None and spec.default is None:
        return None
    try:
        converter = _CONVERTERS[spec.kind]
    except KeyError:  # pragma: no cover - programming error
        raise AssertionError(f"unknown field kind {spec.kind}") from None
    return converter(where, key, value, spec)


def _bool(where: Where, key: str, value: Any, spec: Field) -> Any:
    if not isinstance(value, bool):
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected true or false.")
    return value


def _int(where: Where, key: str, value: Any, spec: Field) -> Any:
    if isinstance(value, bool) or not isinstance(value, int):
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a whole number"
                         f" from {spec.low:g} to {spec.high:g}.")
    check_range(where, key, value, spec)
    return value


def _float(where: Where, key: str, value: Any, spec: Field) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a number"
                         f"{range_text(spec)}.")
    number = float(value)
    if not math.isfinite(number):
        raise where.fail(key, f"got {value!r}; expected a finite number{range_text(spec)}.")
    check_range(where, key, number, spec)
    return number


def _text(where: Where, key: str, value: Any, spec: Field) -> Any:
    if not isinstance(value, str) or not value:
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a non-empty text.")
    if spec.kind == "name" and not NAME_RE.match(value):
        raise where.fail(key, f"got {value!r}; expected a name of letters, digits and '_' that"
                         " starts with a letter (it becomes part of ROS topic names).")
    if spec.choices is not None and value not in spec.choices:
        raise where.fail(key, f"got {value!r}; expected one of {', '.join(spec.choices)}.")
    return value


def _namespace(where: Where, key: str, value: Any, spec: Field) -> Any:
    tokens = value.strip("/").split("/") if isinstance(value, str) else None
    if tokens is None or (value and not all(NAME_RE.match(t) for t in tokens)):
        raise where.fail(key, f"got {value!r}; expected a ROS namespace: names of letters, digits and"
                         " '_' that start with a letter, separated by '/' (e.g. wheels/left), or ''.")
    return value


def _map(where: Where, key: str, value: Any, spec: Field) -> Any:
    if not isinstance(value, Mapping):
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a mapping (key: value).")
    return dict(value)


def _list(where: Where, key: str, value: Any, spec: Field) -> Any:
    if not isinstance(value, list):
        raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a list.")
    return list(value)


def _number(where: Where, key: str, value: Any, spec: Field) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise where.fail(key, f"got {value!r}; expected a finite number (decimal, 0x hex or a real).")
    return value


def _byte_size(where: Where, key: str, value: Any, spec: Field) -> Any:
    if isinstance(value, bool) or not isinstance(value, int) or value not in (1, 2, 4, 8):
        raise where.fail(key, f"got {value!r}; expected 1, 2, 4 or 8 (bytes).")
    return value


def _list_names(where: Where, key: str, value: Any, spec: Field) -> Any:
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise where.fail(key, f"got {value!r}; expected a non-empty list of drive names.")
    return tuple(value)


#: Each field kind's converter (the kinds of :class:`Field`).
_CONVERTERS: dict[str, Callable[[Where, str, Any, Field], Any]] = {
    "bool": _bool, "int": _int, "float": _float, "opt_float": _float, "str": _text, "name": _text, "path": _text,
    "namespace": _namespace, "map": _map, "list": _list, "number": _number, "opt_int": _byte_size,
    "list_names": _list_names,
}


def range_text(spec: Field) -> str:
    if spec.low is None or spec.high is None:
        return ""
    low_op = ">" if spec.low_open else ">="
    return f" {low_op} {spec.low:g} and <= {spec.high:g}"


def check_range(where: Where, key: str, value: float, spec: Field) -> None:
    if spec.low is None or spec.high is None:
        return
    too_low = value <= spec.low if spec.low_open else value < spec.low
    if too_low or value > spec.high:
        raise where.fail(key, f"got {value!r}; expected a value{range_text(spec)}.")


def section(where: Where, prefix: str, data: Any, fields: dict[str, Field]) -> dict[str, Any]:
    if not isinstance(data, Mapping):
        raise where.fail(prefix.rstrip("."), f"got {data!r}; expected a mapping of keys.")
    check_keys(where, prefix, data, tuple(fields))
    out: dict[str, Any] = {}
    for key, spec in fields.items():
        if key in data:
            out[key] = convert(where, prefix + key, data[key], spec)
        elif spec.default is REQUIRED:
            raise where.fail(prefix + key, "missing; this key is required.")
        else:
            out[key] = spec.default
    return out

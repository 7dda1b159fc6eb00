"""The checks that turn a YAML value into a typed one with an error that names the key, and each
section's key table, derived from the dataclass fields that declare the keys
(:mod:`can_config.keys`, :mod:`can_config.model`).

Owner: none; pure checks and values.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.keys import REQUIRED, Field, table
from can_config.model import (
    BusConfig,
    DriveConfig,
    DriveSystemConfig,
    IdentityConfig,
    RecorderConfig,
    SdoSetting,
    SimModelConfig,
    TrajectoryGroupConfig,
)

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


#: Each section's YAML keys, derived from the dataclass fields that declare them (can_config.model).
BUS_FIELDS = table(BusConfig)
IDENTITY_FIELDS = table(IdentityConfig)
DRIVE_FIELDS = table(DriveConfig)
SIM_FIELDS = table(SimModelConfig)
SDO_FIELDS = table(SdoSetting)
DRIVE_SYSTEM_FIELDS = table(DriveSystemConfig)
RECORDER_FIELDS = table(RecorderConfig)
TRAJECTORY_GROUP_FIELDS = table(TrajectoryGroupConfig)
TOP_FIELDS = ("buses", "drives", "drive_system", "recorder", "trajectory_groups")


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


def _variances(where: Where, key: str, value: Any, spec: Field) -> Any:
    ok = isinstance(value, list) and len(value) == 6 and all(
        not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in value)
    if not ok:
        raise where.fail(key, f"got {value!r}; expected a list of six finite numbers over 0 (x, y, z, roll, pitch,"
                         " yaw; a variance of 0 claims a perfect measurement: use 1e6 for what is not measured).")
    return tuple(float(v) for v in value)


#: Each field kind's converter (the kinds of :class:`Field`).
_CONVERTERS: dict[str, Callable[[Where, str, Any, Field], Any]] = {
    "bool": _bool, "int": _int, "float": _float, "opt_float": _float, "str": _text, "name": _text, "path": _text,
    "namespace": _namespace, "map": _map, "list": _list, "number": _number, "opt_int": _byte_size,
    "list_names": _list_names, "variances": _variances,
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

"""A config survives the trip to a dict and back (what a subprocess or a ROS parameter gets):
``parse_config(config_to_dict(c)) == c`` for configs generated from the key table itself, so
a key added to the table without its place in ``config_to_dict`` (or a unit conversion that
does not come back to the same number) fails here."""

from __future__ import annotations

from typing import Any

from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from can_config import config_to_dict, parse_config
from can_config.errors import ConfigError
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

NAMES = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,6}", fullmatch=True)
#: keys whose value is built by the section strategy itself, or fixed to keep the config valid
SPECIAL = {"name", "interface", "channel", "bus", "eds", "kwargs", "identity", "sdo", "sim", "left", "right", "dir", "node_id", "joint",
           "min_deg", "max_deg", "host_timeout_ms", "heartbeat_timeout_ms", "profile_velocity_deg_s"}


def value_of(field: Field) -> st.SearchStrategy[Any]:
    """Any value the key accepts, from its kind, range and choices."""
    if field.choices is not None:
        return st.sampled_from(field.choices)
    if field.kind == "bool":
        return st.booleans()
    if field.kind == "int":
        assert field.low is not None and field.high is not None
        return st.integers(int(field.low), int(field.high))
    if field.kind in ("float", "opt_float"):
        assert field.low is not None and field.high is not None
        number = st.floats(field.low, field.high, exclude_min=field.low_open, allow_nan=False)
        return st.none() | number if field.kind == "opt_float" else number
    if field.kind == "namespace":
        return st.sampled_from(["", "arm", "wheels/left"])
    if field.kind == "number":
        return st.integers(-(2**31), 2**32 - 1) | st.floats(-1e6, 1e6, allow_nan=False)
    if field.kind == "opt_int":
        return st.sampled_from([None, 1, 2, 4, 8])
    if field.kind == "variances":
        return st.lists(st.floats(1e-12, 1e9, allow_nan=False), min_size=6, max_size=6)
    raise AssertionError(f"no strategy for kind {field.kind}")


def section(fields: dict[str, Field], skip: set[str] = SPECIAL) -> st.SearchStrategy[dict[str, Any]]:
    """Each key of a section, present or left out (then its default applies)."""
    keys = {key: value_of(spec) for key, spec in fields.items() if key not in skip}
    return st.fixed_dictionaries({}, optional=keys)


@st.composite
def configs(draw: st.DrawFn) -> dict[str, Any]:
    bus = draw(section(BUS_FIELDS)) | {"name": "can0", "interface": "socketcand", "channel": "can0",
                                       "kwargs": {"host": "127.0.0.1", "port": 29536}}
    host_id = bus.get("host_node_id", 127)
    host_ms = bus.get("host_heartbeat_ms", 50.0)
    drives = []
    for i in range(draw(st.integers(1, 3))):
        drive = draw(section(DRIVE_FIELDS)) | {"name": f"j{i}", "node_id": draw(st.integers(1, 126).filter(lambda n: n != host_id)),
                                              "eds": "generic"}
        drive["node_id"] = drive["node_id"] if drive["node_id"] not in {d["node_id"] for d in drives} else None
        assume(drive["node_id"] is not None)
        if draw(st.booleans()):
            low = draw(st.floats(-1e4, 1e4, allow_nan=False))
            drive |= {"joint": "limited", "min_deg": low, "max_deg": low + draw(st.floats(0.5, 1e4))}
        period = drive.get("heartbeat_period_ms", 100.0)
        drive["heartbeat_timeout_ms"] = draw(st.floats(max(period * 1.001, 20.0), 60_000.0))  # longer than the period
        vmax = drive.get("max_velocity_deg_s", 360.0)
        drive["profile_velocity_deg_s"] = draw(st.floats(0.0, vmax, exclude_min=True))
        drive["host_timeout_ms"] = draw(st.none() | st.floats(max(20.0, host_ms + 1.0), 65_535.0))
        drive["identity"] = draw(section(IDENTITY_FIELDS, set()))
        drive["sim"] = draw(section(SIM_FIELDS, set()))
        drive["sdo"] = draw(st.lists(section(SDO_FIELDS, {"index", "value"}).map(lambda s: s | {"index": 0x2000}).flatmap(
            lambda s: value_of(SDO_FIELDS["value"]).map(lambda v: s | {"value": v})), max_size=2))
        drives.append(drive)
    out: dict[str, Any] = {"buses": [bus], "drives": drives, "recorder": draw(section(RECORDER_FIELDS))}
    if len(drives) > 1 and draw(st.booleans()):  # a wheel is on one side only
        out["drive_system"] = draw(section(DRIVE_SYSTEM_FIELDS)) | {"left": [drives[0]["name"]],
                                                                    "right": [drives[-1]["name"]]}
    return out


def test_every_key_has_a_strategy() -> None:
    """The generator covers the table: a new key with a new kind fails here, not silently."""
    for fields in (BUS_FIELDS, DRIVE_FIELDS, DRIVE_SYSTEM_FIELDS, IDENTITY_FIELDS, RECORDER_FIELDS, SDO_FIELDS, SIM_FIELDS):
        for key, spec in fields.items():
            if key not in SPECIAL and spec.default is not REQUIRED:
                value_of(spec)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(configs())
def test_a_config_comes_back_from_its_dict_unchanged(data: dict[str, Any]) -> None:
    try:
        config = parse_config(data)
    except ConfigError as err:  # the generator keeps the cross-key rules; anything else is a finding
        raise AssertionError(f"a generated config was refused: {err}") from err
    again = parse_config(config_to_dict(config))
    assert again == config
    assert config_to_dict(again) == config_to_dict(config)

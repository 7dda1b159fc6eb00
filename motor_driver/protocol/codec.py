"""The one typed codec of SDO values: an object's bytes by its EDS data type, both ways.

Used by the driver (:mod:`motor_driver.drive.sdo`) and the bench CLI (``rovercan sdo``,
``safety-check``), so that a value reads and writes the same on every path. Pure functions.
"""

from __future__ import annotations

import struct

from canopen.objectdictionary import ObjectDictionary

from can_config.eds import variable
from can_config.objects import STRUCT_FORMAT

FLOAT_FORMATS = ("<f", "<d")


def value_format(od: ObjectDictionary, index: int, subindex: int) -> str | None:
    """The struct format of ``index:subindex`` by its EDS data type; None for an object the EDS
    does not list or whose type has no fixed size (a string, a domain)."""
    var = variable(od, index, subindex)
    return STRUCT_FORMAT.get(int(var.data_type)) if var is not None else None


def unpack_value(fmt: str | None, raw: bytes) -> int | float | None:
    """The number ``raw`` holds in ``fmt``; None where there is no format or the size differs."""
    if fmt is None or len(raw) != struct.calcsize(fmt):
        return None
    value: int | float = struct.unpack(fmt, raw)[0]
    return value


def pack_value(fmt: str, value: int | float) -> bytes:
    """``value`` as ``fmt``'s bytes (a float type takes any number, an integer type a whole one);
    struct.error or OverflowError where it does not fit."""
    return struct.pack(fmt, float(value) if fmt in FLOAT_FORMATS else int(value))

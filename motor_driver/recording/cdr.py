"""CDR of the project's ROS 2 messages (:mod:`motor_driver.recording.ros2defs`), as rclpy serializes them:
pure, no rclpy, from the definitions' own text. The live Foxglove view sends these bytes.

The encoding (OMG CDR, little-endian, as ROS 2's Fast DDS and Cyclone write it): a 4-byte
encapsulation header ``00 01 00 00``; each primitive aligned to its size from the end of that
header; a string as a uint32 length counting its NUL, its UTF-8 bytes and the NUL; a sequence
(``T[]``) as a uint32 count and its elements; a fixed array (``T[N]``) as its N elements; a nested
message as its fields in order. tests/test_cdr.py decodes every type back with mcap-ros2-support's
reader.

Pure functions of their inputs (the parsed definitions are cached: values).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

from can_config.errors import CdrError
from motor_driver.recording.ros2defs import DEFINITIONS

#: Primitive type -> its struct format (its size is its alignment).
PRIMITIVES = {"bool": "?", "byte": "B", "char": "B", "uint8": "B", "int8": "b", "uint16": "H", "int16": "h",
              "uint32": "I", "int32": "i", "uint64": "Q", "int64": "q", "float32": "f", "float64": "d"}
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian
_BYTES = ("byte", "char", "uint8")
_FIELD = re.compile(r"^([A-Za-z][\w/]*)(\[(\d*)\])?\s+([a-z]\w*)\s*(.*)$")


@dataclass(frozen=True)
class Field:
    name: str
    type: str  #: a primitive, ``string`` or a full message type name (``pkg/msg/Type``)
    count: int | None  #: None: one value; -1: a sequence (``T[]``); N: a fixed array (``T[N]``)


@cache
def fields(type_name: str) -> tuple[Field, ...]:
    """The fields of ``type_name`` (a key of :data:`DEFINITIONS`), constants left out."""
    package = type_name.split("/", maxsplit=1)[0]
    out = []
    for text in DEFINITIONS[type_name].splitlines():
        line = text.split("#", 1)[0].strip()
        match = _FIELD.match(line)
        if match is None or "=" in line:
            continue  # blank, a comment or a constant (``byte OK=0``)
        kind, array, size, name = match.group(1), match.group(2), match.group(3), match.group(4)
        if kind not in PRIMITIVES and kind != "string":
            pkg, _, short = kind.rpartition("/")
            kind = f"{pkg or package}/msg/{short}"
            if kind not in DEFINITIONS:
                raise CdrError(f"{type_name}: field {name} of unknown type {match.group(1)!r}")
        out.append(Field(name, kind, None if array is None else int(size) if size else -1))
    return tuple(out)


def encode(type_name: str, message: Mapping[str, Any]) -> bytes:
    """``message`` (field name -> value; nested messages as mappings, ``uint8[]`` as bytes) as the
    CDR of ``type_name``. Raises :class:`CdrError` naming the field that does not fit."""
    out = bytearray(ENCAPSULATION)
    _message(out, type_name, message)
    return bytes(out)


def _align(out: bytearray, size: int) -> None:
    out += bytes(-(len(out) - len(ENCAPSULATION)) % size)


def _message(out: bytearray, type_name: str, message: Mapping[str, Any]) -> None:
    for field in fields(type_name):
        try:
            value = message[field.name]
        except (KeyError, TypeError) as err:
            raise CdrError(f"{type_name}: field {field.name} has no value in {message!r:.200}") from err
        if field.count is None:
            _one(out, field.type, value, type_name, field.name)
            continue
        if field.count < 0:
            _align(out, 4)
            out += struct.pack("<I", len(value))
        elif len(value) != field.count:
            raise CdrError(f"{type_name}: field {field.name} holds {len(value)} values, its type {field.count}")
        if field.type in _BYTES and isinstance(value, (bytes, bytearray)):
            out += value
        else:
            for item in value:
                _one(out, field.type, item, type_name, field.name)


def _one(out: bytearray, kind: str, value: Any, type_name: str, name: str) -> None:
    fmt = PRIMITIVES.get(kind)
    try:
        if fmt is not None:
            if isinstance(value, (bytes, bytearray)) and fmt == "B":
                value = value[0]  # a ``byte`` given as one byte
            size = struct.calcsize(fmt)
            _align(out, size)
            out += struct.pack("<" + fmt, value)
        elif kind == "string":
            data = str(value).encode()
            _align(out, 4)
            out += struct.pack("<I", len(data) + 1) + data + b"\x00"
        else:
            _message(out, kind, value)
    except (struct.error, IndexError) as err:
        raise CdrError(f"{type_name}: field {name} = {value!r:.80} does not fit {kind} ({err})") from err


__all__ = ["ENCAPSULATION", "PRIMITIVES", "CdrError", "Field", "encode", "fields"]

"""CDR of the project's ROS 2 messages (:mod:`motor_driver.recording.ros2defs`), as rclpy serializes them:
pure, no rclpy. The live Foxglove view sends these bytes.

The bytes are mcap-ros2-support's: :func:`encode` calls the encoder its MCAP writer
(``mcap_ros2.writer.Writer``, which writes the recordings) builds from the same definition text, so
the live view and the files cannot differ. That encoder lives in the library's ``_dynamic`` module
(the writer's own import of it); tests/test_cdr.py pins it: every type byte for byte as the writer
puts it in a file, decoded back by mcap-ros2-support's reader and by rosbags.

Measured before replacing the hand-written encoder this module held (the shipped rover's frames
through :class:`~motor_driver.recording.busview.BusView`, every message it emits encoded, best of
four runs on the development machine): 114 us a frame with the library's encoder against 148 us
with the hand-written one (38 us without encoding); per message the library is slower on the
small types (CanFrame 22 us against 12 us) and faster on MotorState, the view's most frequent.
No measured reason to keep a copy.

Refusals: a message without one of its type's fields, or with a value its field's type cannot
hold, raises :class:`CdrError` naming the field (:func:`misfit` finds it; it runs only when the
library refused a message or a field of the top level is missing). A field missing from a nested
message takes its type's default, as rclpy's message constructors and the MCAP writer give it.

Pure functions of their inputs (the parsed definitions and encoders are cached: values).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

from mcap_ros2._dynamic import serialize_dynamic

from can_config.errors import CdrError
from motor_driver.recording.ros2defs import DEFINITIONS, schema_text

#: Primitive type -> its struct format, to name the field whose value does not fit.
PRIMITIVES = {"bool": "?", "byte": "B", "char": "B", "uint8": "B", "int8": "b", "uint16": "H", "int16": "h",
              "uint32": "I", "int32": "i", "uint64": "Q", "int64": "q", "float32": "f", "float64": "d"}
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian
_FIELD = re.compile(r"^([A-Za-z][\w/]*)(\[(\d*)\])?\s+([a-z]\w*)\s*(.*)$")
#: What mcap-ros2-support's encoder raises for a value its field cannot hold.
_REFUSED = (struct.error, ValueError, TypeError, AttributeError, IndexError, KeyError)


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


@cache
def _encoder(type_name: str) -> tuple[Callable[[Any], bytes], frozenset[str]]:
    """mcap-ros2-support's encoder of ``type_name`` and the names of its fields."""
    if type_name not in DEFINITIONS:
        raise CdrError(f"{type_name}: not a type of the project's definitions ({', '.join(sorted(DEFINITIONS))})")
    return serialize_dynamic(type_name, schema_text(type_name))[type_name], frozenset(f.name for f in fields(type_name))


def encode(type_name: str, message: Mapping[str, Any]) -> bytes:
    """``message`` (field name -> value; nested messages as mappings, ``uint8[]`` as bytes) as the
    CDR of ``type_name``. Raises :class:`CdrError` naming the field that does not fit."""
    encoder, names = _encoder(type_name)
    try:
        if names <= message.keys():
            return encoder(message)
        err: BaseException | None = None
    except _REFUSED as refused:
        err = refused
    raise CdrError(f"{type_name}: {misfit(type_name, message) or f'refused by the encoder ({err})'}") from err


def misfit(type_name: str, message: Any) -> str | None:
    """The first field of ``message`` that ``type_name`` cannot take, said ("field dlc has no
    value", "field id = -1 does not fit uint32 (...)"), or None."""
    for field in fields(type_name):
        try:
            value = message[field.name]
        except (KeyError, TypeError):
            return f"field {field.name} has no value in {message!r:.200}"
        items = [value] if field.count is None else value
        if field.count is not None and field.count >= 0 and len(value) != field.count:
            return f"field {field.name} holds {len(value)} values, its type {field.count}"
        if field.count is not None and isinstance(value, (bytes, bytearray)) and PRIMITIVES.get(field.type) == "B":
            continue
        for item in items:
            said = _item_misfit(field, item)
            if said is not None:
                return said
    return None


def _item_misfit(field: Field, item: Any) -> str | None:
    fmt = PRIMITIVES.get(field.type)
    if fmt is not None:
        try:
            struct.pack("<" + fmt, item)
        except (struct.error, TypeError) as err:
            return f"field {field.name} = {item!r:.80} does not fit {field.type} ({err})"
        return None
    if field.type == "string":
        return None  # the encoder takes any value as its str()
    inner = misfit(field.type, item)
    return None if inner is None else f"field {field.name}.{inner.removeprefix('field ')}"


__all__ = ["ENCAPSULATION", "PRIMITIVES", "CdrError", "Field", "encode", "fields", "misfit"]

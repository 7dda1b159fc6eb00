"""A command topic's std_msgs/Float32 taken raw (its serialized CDR bytes) and decoded here.

rclpy's own conversion builds a Python message object for every message taken (about 4 us of
the hot executor's time a command on the development machine): at six drives commanded at
500 Hz (docs/performance.md) that is 3,000 objects a second made to read one float.
A Float32 is four bytes of encapsulation header and the float: read here, from the header's
byte order. Anything else (another encapsulation, a short payload) is refused with what came.

Owner: none; a pure decode, on the hot executor's thread that takes the message.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from can_config.errors import CommandRejected

_LITTLE = struct.Struct("<f").unpack_from
_BIG = struct.Struct(">f").unpack_from
#: The CDR encapsulation kinds (the header's first two bytes) a Float32 comes in, and the byte
#: order each says: XCDR1 (CDR_BE, CDR_LE) and XCDR2 plain (PLAIN_CDR2_BE, PLAIN_CDR2_LE); a
#: float32 struct is the same four bytes after the header in all four.
ENCAPSULATIONS: dict[bytes, Callable[[bytes, int], tuple[float]]] = {
    b"\x00\x00": _BIG, b"\x00\x01": _LITTLE, b"\x00\x06": _BIG, b"\x00\x07": _LITTLE}


def float32_data(raw: bytes, topic: str) -> float:
    """The ``data`` of a serialized std_msgs/Float32 from ``topic``; CommandRejected naming what came otherwise."""
    unpack = ENCAPSULATIONS.get(raw[:2]) if len(raw) >= 8 else None
    if unpack is None:
        raise CommandRejected(f"{topic}: a std_msgs/Float32 of {len(raw)} bytes starting {raw[:4].hex()} is not a"
                              " CDR-serialized Float32 (4 bytes of header, 4 of float); publish std_msgs/Float32."
                              " Nothing was sent.")
    return unpack(raw, 4)[0]

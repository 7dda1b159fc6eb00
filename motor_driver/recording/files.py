"""Reading CAN recordings (every format python-can reads, and ``candump -L`` output as .txt):
read in full before anything is done with them (a file that breaks half way never
half-replays), each frame checked, and a damaged file answered with one :class:`ConfigError`
naming the file, the format and what is wrong, never a reader's own exception.

Owner: the calling thread; no state kept between calls.
"""

from __future__ import annotations

import logging
import math
import re
import sqlite3
import struct
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
from can.io.blf import BLFParseError

from can_config.errors import ConfigError
from can_config.textfile import check_text_file

logger = logging.getLogger(__name__)

TEXT_RECORDINGS = (".asc", ".csv", ".log", ".trc", ".txt")
#: A recording holds at most this many frames (about 1 GB of python-can messages): a bench or
#: incident recording is far smaller; past it, split the file (python -m can.logconvert).
FRAMES_MAX = 2_000_000
#: One BLF container inflates to at most this much: python-can writes 128 KiB containers, Vector
#: tools about that; a container that inflates past it is a zip bomb or damage.
BLF_CONTAINER_MAX = 16 * 1024 * 1024
_BLF_FILE_HEADER = struct.Struct("<4sL")
_BLF_OBJ_HEADER = struct.Struct("<4sHHLL")  # LOBJ, header size, version, object size, object type
_BLF_LOG_CONTAINER = 10
_BLF_ZLIB = 2
#: What python-can's readers raise on a damaged file (a truncated or bit-flipped BLF, a .db that
#: is no database, a text line that does not parse).
RECORDING_ERRORS: tuple[type[BaseException], ...] = (
    ValueError, UnicodeDecodeError, struct.error, IndexError, KeyError, OSError, EOFError, TypeError,
    AttributeError, OverflowError, BLFParseError, zlib.error, sqlite3.Error, can.CanError)
STANDARD_ID_MAX = 0x7FF
EXTENDED_ID_MAX = 0x1FFF_FFFF
FD_DATA_MAX = 64


def recording_readers() -> dict[str, Callable[[str], Any]]:
    return {**can.io.player.MESSAGE_READERS, ".txt": can.CanutilsLogReader}


def frame_problem(msg: can.Message) -> str | None:
    """What makes a read frame impossible on a bus (None: it is a frame). A reader gives what the
    file holds: a damaged .db gives any type in any column."""
    if not isinstance(msg.arbitration_id, int) or isinstance(msg.arbitration_id, bool):
        return f"id {msg.arbitration_id!r} is not a number"
    if not isinstance(msg.data, (bytes, bytearray)):
        return f"data {msg.data!r} is not bytes"
    if not isinstance(msg.timestamp, (int, float)) or not isinstance(msg.dlc, int):
        return f"timestamp {msg.timestamp!r} or length {msg.dlc!r} is not a number"
    top = EXTENDED_ID_MAX if msg.is_extended_id else STANDARD_ID_MAX
    if not 0 <= msg.arbitration_id <= top:
        kind = "an extended" if msg.is_extended_id else "a standard"
        return f"id 0x{msg.arbitration_id:X} does not fit {kind} frame (0 to 0x{top:X})"
    if len(msg.data) > FD_DATA_MAX:
        return f"{len(msg.data)} data bytes (at most {FD_DATA_MAX})"
    if not math.isfinite(msg.timestamp):
        return f"timestamp {msg.timestamp}"
    return None


#: candump's screen output ("  can0  701   [1]  05"): interface, id, [dlc], bytes, no timestamp.
CANDUMP_SCREEN = re.compile(r"^\s*\S+\s+[0-9A-Fa-f]{3,8}\s+\[\d\]")


def _hint(file: Path, suffix: str) -> str:
    """What the file looks like instead, when it can be told."""
    if suffix in TEXT_RECORDINGS:
        try:
            with file.open(encoding="utf-8", errors="replace") as text:
                first = text.readline()
        except OSError:
            return ""
        if CANDUMP_SCREEN.match(first):
            return ("; it looks like candump's screen output, which has no times: record with"
                    " `candump -L can0 > session.log` (python-can reads that)")
    return ""


def blf_problem(file: Path) -> str | None:
    """What makes a BLF file unsafe to hand to python-can's reader, which trusts every size in
    it: an object larger than what is left of the file (it would read, and allocate, that much),
    or a container that inflates past BLF_CONTAINER_MAX (checked by inflating it, bounded: the
    size it declares may lie). None when it is sound."""
    size = file.stat().st_size
    with file.open("rb") as blf:
        head = blf.read(_BLF_FILE_HEADER.size)
        if len(head) < _BLF_FILE_HEADER.size or head[:4] != b"LOGG":
            return "it does not start as a BLF file (LOGG)"
        pos = _BLF_FILE_HEADER.unpack(head)[1]
        while pos < size:
            blf.seek(pos)
            base = blf.read(_BLF_OBJ_HEADER.size)
            if len(base) < _BLF_OBJ_HEADER.size:
                return None  # a truncated tail: python-can stops there
            signature, _, _, obj_size, obj_type = _BLF_OBJ_HEADER.unpack(base)
            if signature != b"LOBJ" or obj_size < _BLF_OBJ_HEADER.size or pos + obj_size > size:
                return f"an object at byte {pos} claims {obj_size} bytes, past the end of the file"
            if obj_type == _BLF_LOG_CONTAINER:
                body = blf.read(obj_size - _BLF_OBJ_HEADER.size)
                if len(body) >= 16 and int.from_bytes(body[:2], "little") == _BLF_ZLIB:
                    inflate = zlib.decompressobj()
                    try:
                        inflate.decompress(body[16:], BLF_CONTAINER_MAX)
                    except zlib.error:
                        return f"the container at byte {pos} does not inflate (damaged)"
                    if inflate.unconsumed_tail:
                        return (f"the container at byte {pos} inflates past {BLF_CONTAINER_MAX // (1024 * 1024)} MiB"
                                " (a zip bomb, or damage)")
            pos += obj_size + obj_size % 4
    return None


def _sqlite_problem(file: Path) -> str | None:
    """python-can reads the table ``messages``; a view of that name may never end (a recursive
    one), so only a table is read."""
    try:
        with sqlite3.connect(f"file:{file}?mode=ro", uri=True) as db:
            row = db.execute("SELECT type FROM sqlite_master WHERE name = 'messages'").fetchone()
    except (sqlite3.Error, UnicodeDecodeError) as err:  # a damaged schema's text need not be UTF-8
        return f"not a database python-can reads ({' '.join(str(err).split())})"  # one line, whatever it quotes
    if row is None:
        return "no table 'messages' (python-can's sqlite recordings have one)"
    if row[0] != "table":
        return f"'messages' is a {row[0]}, not a table: only a table is read (a view may never end)"
    return None


def read_recording(path: str) -> list[can.Message]:
    """Every frame of a recording, or :class:`ConfigError` naming the file and what is wrong."""
    frames: list[can.Message] = []
    for msg in iter_recording(path):
        if len(frames) == FRAMES_MAX:
            raise ConfigError(f"{path}: more than {FRAMES_MAX:,} frames; split it first"
                              " (python -m can.logconvert) or give a shorter recording")
        frames.append(msg)
    return frames


def iter_recording(path: str) -> Iterator[can.Message]:
    """The frames of a recording as they are read (any length, in bounded memory), each checked;
    :class:`ConfigError` naming the file and what is wrong, at the frame where it is found."""
    file = Path(path)
    readers = recording_readers()
    suffix = file.suffix.lower()
    if suffix not in readers:
        raise ConfigError(f"{path}: {suffix or 'a file without suffix'} is not a recording format python-can reads;"
                          f" use one of {', '.join(sorted(readers))} (candump -L output: .log or .txt)")
    if not file.is_file():
        raise ConfigError(f"{path}: no such recording (or not a regular file)")
    if suffix in TEXT_RECORDINGS:
        check_text_file(file, "recording", "give a recording")  # binary or UTF-16 content is named, in pieces
    unsafe = blf_problem(file) if suffix == ".blf" else _sqlite_problem(file) if suffix == ".db" else None
    if unsafe:
        raise ConfigError(f"{path}: not read: {unsafe}")
    n = 0
    try:
        with readers[suffix](path) as reader:
            for msg in reader:
                n += 1
                if problem := frame_problem(msg):
                    raise ConfigError(f"{path}: frame {n} of this {suffix} recording is damaged: {problem}")
                yield msg
    except ConfigError:
        raise
    except NotImplementedError as err:  # a reader whose optional package is missing (.mf4: asammdf)
        raise ConfigError(f"{path}: python-can cannot read {suffix} files here ({err})") from err
    except RECORDING_ERRORS as err:
        logger.debug("%s: %s reader: %r", path, suffix, err)  # Python's words for it: not for the user
        raise ConfigError(f"{path}: not a valid {suffix} recording, the file is damaged or of another format"
                          f"{_hint(file, suffix)}") from err
    if not n:
        raise ConfigError(f"{path}: no CAN frames in this {suffix} file")

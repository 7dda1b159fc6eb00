"""EDS loading and checking, shared (as passive data) by the driver and the emulator.

The EDS is parsed by the python ``canopen`` library's importer; this module turns parse
failures into :class:`EdsError` with the file name, and checks that a file describes a
CiA 402 drive the stack can run (the objects it needs, and whether they can be PDO-mapped).

Owner: none; values only, and pure functions of a file's text.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from can_config.errors import ConfigError, EdsError
from can_config.objects import OD
from can_config.textfile import check_regular_file

logger = logging.getLogger(__name__)

#: Objects without which a drive cannot be run by this stack.
REQUIRED_OBJECTS: dict[int, str] = {
    OD.CONTROLWORD: "controlword",
    OD.STATUSWORD: "statusword",
    OD.MODES_OF_OPERATION: "modes of operation",
    OD.MODES_OF_OPERATION_DISPLAY: "modes of operation display",
    OD.POSITION_ACTUAL: "position actual value",
}

#: The largest vendor EDS files are a few hundred kB.
EDS_MAX_BYTES = 16 << 20


def load_od(path: Path | str, node_id: int = 1) -> ObjectDictionary:
    """Parse an EDS (``$NODEID`` resolved for ``node_id``). Raises :class:`EdsError`."""
    try:
        resolved = Path(path).resolve()
    except (OSError, RuntimeError) as err:  # a symlink loop: RuntimeError before Python 3.13
        raise EdsError(f"{path}: cannot resolve the EDS path ({err}); check its symlinks.") from err
    return _load_od_cached(str(resolved), node_id)


@functools.lru_cache(maxsize=64)
def _load_od_cached(path: str, node_id: int) -> ObjectDictionary:
    source = Path(path)
    if not source.exists():
        raise EdsError(f"{path}: EDS file not found; give an existing .eds path, or 'generic'"
                       " for the project's own CiA 402 EDS.")
    try:
        check_regular_file(source, "EDS", EDS_MAX_BYTES)
    except ConfigError as err:
        raise EdsError(str(err)) from err
    try:
        od = canopen.import_od(path, node_id)
    except Exception as err:  # the importer raises anything from configparser to ValueError
        raise EdsError(f"{path}: cannot parse the EDS ({type(err).__name__}: {err}).") from err
    if len(od) == 0:
        raise EdsError(f"{path}: the EDS holds no objects; is it really an EDS file?")
    return od


def has_object(od: ObjectDictionary, index: int, subindex: int | None = None) -> bool:
    try:
        obj = od[index]
    except KeyError:
        return False
    if subindex is None:
        return True
    if isinstance(obj, (ODRecord, ODArray)):
        try:
            obj[subindex]
        except KeyError:
            return False
        return True
    return subindex == 0


def variable(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable | None:
    """The variable at index/subindex, or ``None`` where the EDS lacks it."""
    try:
        obj = od[index]
        if isinstance(obj, (ODRecord, ODArray)):
            var = obj[subindex]
        else:
            var = obj
    except KeyError:
        return None
    return var if isinstance(var, ODVariable) else None


def check_cia402(od: ObjectDictionary, path: Path | str) -> None:
    """Refuse an EDS that cannot be a CiA 402 drive, naming what is missing."""
    missing = [f"0x{idx:04X} {name}" for idx, name in REQUIRED_OBJECTS.items()
               if not has_object(od, idx)]
    if missing:
        raise EdsError(f"{path}: not a usable CiA 402 drive: the EDS lacks {', '.join(missing)}."
                       " Use the EDS of the drive itself (or 'generic').")


def consumer_subs(od: ObjectDictionary) -> tuple[int, ...]:
    """The sub-indexes of the consumer heartbeat entries (0x1016:1..n) the EDS defines."""
    try:
        obj = od[0x1016]
    except KeyError:
        return ()
    if not isinstance(obj, (ODRecord, ODArray)):
        return ()
    return tuple(sorted(sub for sub in obj.subindices if sub > 0))


def count_pdos(od: ObjectDictionary, comm_base: int) -> int:
    """How many PDOs (communication + mapping objects both present) the EDS defines."""
    map_base = comm_base + 0x200
    n = 0
    while n < 512 and has_object(od, comm_base + n) and has_object(od, map_base + n):
        n += 1
    return n


def load_drive_od(path: Path | str, node_id: int = 1) -> ObjectDictionary:
    """Load an EDS and check that it is a CiA 402 drive."""
    od = load_od(path, node_id)
    check_cia402(od, path)
    return od

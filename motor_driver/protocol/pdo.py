"""The PDO set the driver needs, planned from a drive's EDS, and its codecs (pure).

The driver never trusts vendor default mappings: :func:`plan_pdos` decides which objects go
in which PDO, :func:`mapping_writes` lists the SDO writes that configure them with the CiA
301 procedure (invalidate, clear count, write entries, set count, set transmission type,
validate), and :class:`TpdoLayout` decodes received TPDOs with one precompiled struct.
Objects a drive cannot PDO-map are left to SDO, with a warning.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property

from canopen.objectdictionary import ObjectDictionary

from can_config.eds import count_pdos, variable
from can_config.objects import (
    OD,
    PDO_COB_ID_INVALID,
    RPDO_BASES,
    STRUCT_FORMAT,
    SUPPORTED_MODE_BIT,
    TPDO_BASES,
    OperationMode,
)

TT_SYNC = 1  # synchronous, every SYNC
TT_EVENT = 255  # event-driven (device profile specific: on change)


@dataclass(frozen=True)
class PdoMap:
    """One PDO: its number (0-based), COB-ID, transmission type and mapped objects."""

    number: int
    cob_id: int
    trans_type: int
    objects: tuple[tuple[int, int, int], ...]  # (index, subindex, data type)
    inhibit_100us: int = 0
    event_timer_ms: int = 0

    # cached: these sit on the command hot path (every RPDO is packed with them)
    @cached_property
    def struct_format(self) -> str:
        return "<" + "".join(STRUCT_FORMAT[dt][1:] for _, _, dt in self.objects)

    @cached_property
    def codec(self) -> struct.Struct:
        return struct.Struct(self.struct_format)

    @cached_property
    def indexes(self) -> tuple[int, ...]:
        return tuple(i for i, _, _ in self.objects)


@dataclass(frozen=True)
class PdoPlan:
    rpdos: tuple[PdoMap, ...]
    tpdos: tuple[PdoMap, ...]
    n_rpdo: int
    n_tpdo: int
    node_id: int
    sdo_only: tuple[int, ...] = field(default=())  # objects that must go by SDO

    def rpdo_with(self, index: int) -> PdoMap | None:
        for pdo in self.rpdos:
            if index in pdo.indexes:
                return pdo
        return None


def _mappable(od: ObjectDictionary, index: int, subindex: int = 0) -> int | None:
    """Data type of a PDO-mappable fixed-size object, else ``None``."""
    var = variable(od, index, subindex)
    if var is None or not var.pdo_mappable or int(var.data_type) not in STRUCT_FORMAT:
        return None
    return int(var.data_type)


def _eds_lists_mode(od: ObjectDictionary, mode: OperationMode) -> bool:
    var = variable(od, OD.SUPPORTED_DRIVE_MODES)
    value = var.default if var is not None else None
    return isinstance(value, int) and bool(value >> SUPPORTED_MODE_BIT[mode] & 1)


def plan_pdos(od: ObjectDictionary, node_id: int) -> PdoPlan:
    """The PDOs the driver configures on this drive.

    RPDO1 controlword; RPDO2 controlword + target position; RPDO3 controlword + target
    velocity; RPDO4 controlword + target torque; on a drive whose EDS lists interpolated
    position but not CSP (0x6502), controlword + interpolation set-point (0x60C1:1) where an
    RPDO is left. TPDO1 statusword + mode display on change; TPDO2 position + velocity on SYNC;
    TPDO3 torque + statusword on SYNC.

    Pure (no log): objects that cannot be mapped are in ``sdo_only``; the drive says so once.
    """
    n_rpdo = count_pdos(od, OD.RPDO_COMM)
    n_tpdo = count_pdos(od, OD.TPDO_COMM)
    sdo_only: list[int] = []

    def entries(*objects: int | tuple[int, int]) -> tuple[tuple[int, int, int], ...]:
        out = []
        for obj in objects:
            index, sub = obj if isinstance(obj, tuple) else (obj, 0)
            dt = _mappable(od, index, sub)
            if dt is None:
                if variable(od, index, sub) is not None:
                    sdo_only.append(index)
                continue
            out.append((index, sub, dt))
        return tuple(out)

    wanted_r = [entries(OD.CONTROLWORD),
                entries(OD.CONTROLWORD, OD.TARGET_POSITION),
                entries(OD.CONTROLWORD, OD.TARGET_VELOCITY),
                entries(OD.CONTROLWORD, OD.TARGET_TORQUE)]
    if _eds_lists_mode(od, OperationMode.INTERPOLATED_POSITION) and not _eds_lists_mode(od, OperationMode.CYCLIC_SYNC_POSITION):
        wanted_r.append(entries(OD.CONTROLWORD, (OD.INTERPOLATION_DATA, 1)))
    wanted_t = [(entries(OD.STATUSWORD, OD.MODES_OF_OPERATION_DISPLAY), TT_EVENT),
                (entries(OD.POSITION_ACTUAL, OD.VELOCITY_ACTUAL), TT_SYNC),
                (entries(OD.TORQUE_ACTUAL, OD.STATUSWORD), TT_SYNC)]
    rpdos: list[PdoMap] = []
    seen: set[tuple[int, ...]] = set()
    for objs in wanted_r:
        key = tuple(i for i, _, _ in objs)
        if not objs or key in seen or len(rpdos) >= n_rpdo:
            continue
        seen.add(key)
        n = len(rpdos)
        rpdos.append(PdoMap(n, RPDO_BASES[n] + node_id if n < 4 else 0, TT_EVENT, objs))
    tpdos: list[PdoMap] = []
    for objs, tt in wanted_t:
        if not objs or len(tpdos) >= n_tpdo:
            continue
        if objs == ((OD.STATUSWORD, 0, objs[0][2]),) and tpdos and tt == TT_SYNC:
            continue  # a SYNC TPDO with only the statusword adds nothing to TPDO1
        n = len(tpdos)
        tpdos.append(PdoMap(n, TPDO_BASES[n] + node_id if n < 4 else 0, tt, objs,
                            inhibit_100us=0, event_timer_ms=0))
    return PdoPlan(tuple(rpdos), tuple(tpdos), n_rpdo, n_tpdo, node_id, tuple(sorted(set(sdo_only))))


def _u32(value: int) -> bytes:
    return struct.pack("<I", value)


def mapping_writes(plan: PdoPlan) -> list[tuple[int, int, bytes, str]]:
    """Every SDO write (index, subindex, data, what) that configures the plan, in order.

    PDOs the plan does not use are invalidated, so the drive sends nothing the driver did not
    ask for (vendor defaults often leave TPDOs enabled).
    """
    writes: list[tuple[int, int, bytes, str]] = []
    for comm_base, bases, used, total in ((OD.RPDO_COMM, RPDO_BASES, plan.rpdos, plan.n_rpdo),
                                          (OD.TPDO_COMM, TPDO_BASES, plan.tpdos, plan.n_tpdo)):
        map_base = comm_base + 0x200
        kind = "RPDO" if comm_base == OD.RPDO_COMM else "TPDO"
        for n in range(min(total, 4)):
            comm, mapping = comm_base + n, map_base + n
            pdo = next((p for p in used if p.number == n), None)
            cob = pdo.cob_id if pdo is not None else bases[n] + plan.node_id
            writes.append((comm, 1, _u32(cob | PDO_COB_ID_INVALID), f"{kind}{n + 1} invalidate"))
            if pdo is None:
                continue
            writes.append((mapping, 0, b"\x00", f"{kind}{n + 1} clear mapping"))
            for sub, (index, subindex, dt) in enumerate(pdo.objects, start=1):
                bits = struct.calcsize(STRUCT_FORMAT[dt]) * 8
                entry = (index << 16) | (subindex << 8) | bits
                writes.append((mapping, sub, _u32(entry), f"{kind}{n + 1} map 0x{index:04X}"))
            writes.append((mapping, 0, bytes([len(pdo.objects)]), f"{kind}{n + 1} mapping count"))
            writes.append((comm, 2, bytes([pdo.trans_type]), f"{kind}{n + 1} transmission type"))
            writes.append((comm, 1, _u32(cob), f"{kind}{n + 1} validate"))
    return writes


@dataclass(frozen=True)
class TpdoLayout:
    """How to decode one TPDO: a precompiled struct and the object each field is."""

    cob_id: int
    codec: struct.Struct
    indexes: tuple[int, ...]

    @classmethod
    def from_map(cls, pdo: PdoMap) -> TpdoLayout:
        return cls(pdo.cob_id, pdo.codec, pdo.indexes)


def encode_rpdo(pdo: PdoMap, values: Mapping[int, int]) -> bytes:
    """Payload of an RPDO from object values (pure; exact-byte tested)."""
    return pdo.codec.pack(*(values[i] for i in pdo.indexes))

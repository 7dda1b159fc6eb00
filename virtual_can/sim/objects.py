"""The simulated drive's object dictionary: values with data types, access and defaults.

Built from an EDS (parsed by ``can_config``), written and read by the SDO server and by
the drive's own logic. Errors are :class:`SdoAbort` with the CiA 301 abort code, which the
SDO server turns into an abort frame.

Owner: the simulator's runner thread, all of it.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from can_config.objects import DATA_TYPE_SIZE, OD, STRUCT_FORMAT, DataType

logger = logging.getLogger(__name__)

Value = int | float | bytes

ABORT_NO_OBJECT = 0x0602_0000
ABORT_NO_SUBINDEX = 0x0609_0011
ABORT_READ_ONLY = 0x0601_0002
ABORT_WRITE_ONLY = 0x0601_0001
ABORT_LENGTH = 0x0607_0010
ABORT_VALUE_HIGH = 0x0609_0031
ABORT_VALUE_LOW = 0x0609_0032
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_LENGTH = 0x0604_0042
ABORT_DEVICE_STATE = 0x0800_0022
ABORT_GENERAL = 0x0800_0000
ABORT_INVALID_VALUE = 0x0609_0030

#: Values the simulator uses where an EDS gives no default (e.g. maxon EPOS4 leaves 0x1000
#: and 0x6502 to the device).
FALLBACK_DEFAULTS: dict[tuple[int, int], Value] = {
    (OD.DEVICE_TYPE, 0): 0x0002_0192,
    (OD.SUPPORTED_DRIVE_MODES, 0): 0b1010_1101,  # PP, PV, PT, homing, CSP
    (OD.FOLLOWING_ERROR_WINDOW, 0): 20_000,
    (OD.FOLLOWING_ERROR_TIMEOUT, 0): 100,
    (OD.MAX_TORQUE, 0): 3000,
    (OD.QUICK_STOP_OPTION, 0): 2,
    (OD.PROFILE_VELOCITY, 0): 4096,
    (OD.PROFILE_ACCELERATION, 0): 16384,
    (OD.PROFILE_DECELERATION, 0): 16384,
    (OD.QUICK_STOP_DECELERATION, 0): 65536,
    (OD.MAX_PROFILE_VELOCITY, 0): 10_000_000,
}


class SdoAbort(Exception):
    """An access the object dictionary refuses, with its CiA 301 abort code."""

    def __init__(self, code: int, index: int, subindex: int, why: str = "") -> None:
        super().__init__(f"SDO abort 0x{code:08X} on 0x{index:04X}:{subindex}: {why}")
        self.code = code
        self.index = index
        self.subindex = subindex


@dataclass
class SimVariable:
    index: int
    subindex: int
    name: str
    data_type: int
    access: str
    mappable: bool
    default: Value
    low: float | None = None
    high: float | None = None

    @property
    def readable(self) -> bool:
        return self.access != "wo"

    @property
    def writable(self) -> bool:
        return self.access in ("rw", "wo", "rww", "rwr")

    @property
    def size_bits(self) -> int:
        return DATA_TYPE_SIZE.get(self.data_type, 0) * 8


def _zero(data_type: int) -> Value:
    if data_type in (DataType.REAL32, DataType.REAL64):
        return 0.0
    if data_type in (DataType.VISIBLE_STRING, DataType.OCTET_STRING, DataType.UNICODE_STRING,
                     DataType.DOMAIN):
        return b""
    return 0


def encode(data_type: int, value: Value) -> bytes:
    """Little-endian encoding of a value of a CiA 301 data type."""
    fmt = STRUCT_FORMAT.get(data_type)
    if fmt is not None:
        if data_type in (DataType.REAL32, DataType.REAL64):
            return struct.pack(fmt, float(value))  # type: ignore[arg-type]
        return struct.pack(fmt, int(value))  # type: ignore[arg-type]
    if data_type in (DataType.INTEGER24, DataType.UNSIGNED24):
        return int(value).to_bytes(3, "little", signed=data_type == DataType.INTEGER24)  # type: ignore[arg-type]
    if isinstance(value, bytes):
        return value
    return str(value).encode("latin-1")


def decode(data_type: int, raw: bytes) -> Value:
    fmt = STRUCT_FORMAT.get(data_type)
    if fmt is not None:
        return struct.unpack(fmt, raw)[0]  # type: ignore[no-any-return]
    if data_type in (DataType.INTEGER24, DataType.UNSIGNED24):
        return int.from_bytes(raw, "little", signed=data_type == DataType.INTEGER24)
    return bytes(raw)


class ObjectStore:
    """Values of every variable of an EDS, keyed by (index, subindex)."""

    def __init__(self, od: ObjectDictionary) -> None:
        self.od = od
        self.vars: dict[tuple[int, int], SimVariable] = {}
        self.values: dict[tuple[int, int], Value] = {}
        self.on_write: Callable[[int, int], None] | None = None
        self.saved: dict[tuple[int, int], Value] = {}  # 0x1010 "save": survives resets and power cycles
        for obj in od.values():
            members = list(obj.values()) if isinstance(obj, (ODRecord, ODArray)) else [obj]
            for var in members:
                if isinstance(var, ODVariable):
                    self._add(var)
        self.reset(0x0000, 0xFFFF)

    def _add(self, var: ODVariable) -> None:
        key = (var.index, var.subindex)
        default = var.default
        if default is None:
            default = self._device_info(key)
        if default is None:
            default = FALLBACK_DEFAULTS.get(key, _zero(var.data_type))
        elif isinstance(default, str):
            default = default.encode("latin-1")
        elif isinstance(default, bytearray):
            default = bytes(default)
        elif isinstance(default, bool):
            default = int(default)
        if isinstance(default, int) and var.data_type in STRUCT_FORMAT:
            default = _fit(var.data_type, default)
        self.vars[key] = SimVariable(var.index, var.subindex, var.name, int(var.data_type),
                                     var.access_type or "rw", bool(var.pdo_mappable), default,
                                     var.min, var.max)

    def _device_info(self, key: tuple[int, int]) -> Value | None:
        """Identity and name from the EDS's [DeviceInfo] where the objects carry no default (a
        real drive answers with its own; the EPOS4 file has them only there)."""
        info = self.od.device_information
        fields: dict[tuple[int, int], object] = {
            (OD.IDENTITY, 1): info.vendor_number, (OD.IDENTITY, 2): info.product_number,
            (OD.IDENTITY, 3): info.revision_number, (OD.DEVICE_NAME, 0): info.product_name}
        value = fields.get(key)
        if isinstance(value, str):
            return value.encode("latin-1", "replace")
        return value if isinstance(value, int) else None

    def reset(self, low: int, high: int) -> None:
        """Restore the objects from ``low`` to ``high`` (NMT reset node / comm): their saved
        values (0x1010) where there are some, else the EDS defaults."""
        for key, var in self.vars.items():
            if low <= key[0] <= high:
                self.values[key] = self.saved.get(key, var.default)

    def save(self, low: int, high: int) -> int:
        """0x1010 "save": keep the current values of ``low`` to ``high``; how many were kept."""
        kept = {key: value for key, value in self.values.items()
                if low <= key[0] <= high and key[0] != 0x1010 and self.vars[key].writable}
        self.saved.update(kept)
        return len(kept)

    def has(self, index: int, subindex: int = 0) -> bool:
        return (index, subindex) in self.vars

    def var(self, index: int, subindex: int) -> SimVariable:
        var = self.vars.get((index, subindex))
        if var is None:
            if any(k[0] == index for k in self.vars):
                raise SdoAbort(ABORT_NO_SUBINDEX, index, subindex, "no such sub-index")
            raise SdoAbort(ABORT_NO_OBJECT, index, subindex, "no such object")
        return var

    def get(self, index: int, subindex: int = 0, default: Value = 0) -> Value:
        return self.values.get((index, subindex), default)

    def set(self, index: int, subindex: int, value: Value) -> None:
        """Internal write (the drive's own logic): no access checks, no hooks."""
        if (index, subindex) in self.vars:
            self.values[(index, subindex)] = value

    def read(self, index: int, subindex: int) -> bytes:
        """SDO upload of one variable."""
        var = self.var(index, subindex)
        if not var.readable:
            raise SdoAbort(ABORT_WRITE_ONLY, index, subindex, "write-only object")
        return encode(var.data_type, self.values[(index, subindex)])

    def write(self, index: int, subindex: int, raw: bytes) -> None:
        """SDO download of one variable, checked as a device would; runs the write hook."""
        var = self.var(index, subindex)
        if not var.writable:
            raise SdoAbort(ABORT_READ_ONLY, index, subindex, "read-only object")
        size = DATA_TYPE_SIZE.get(var.data_type)
        if size is not None and len(raw) != size:
            raise SdoAbort(ABORT_LENGTH, index, subindex,
                           f"{len(raw)} bytes written, the object has {size}")
        value = decode(var.data_type, raw)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if var.high is not None and value > var.high:
                raise SdoAbort(ABORT_VALUE_HIGH, index, subindex, f"{value} > {var.high}")
            if var.low is not None and value < var.low:
                raise SdoAbort(ABORT_VALUE_LOW, index, subindex, f"{value} < {var.low}")
        old = self.values.get((index, subindex))
        self.values[(index, subindex)] = value
        if self.on_write is not None:
            try:
                self.on_write(index, subindex)
            except SdoAbort:
                if old is not None:
                    self.values[(index, subindex)] = old
                raise


def _fit(data_type: int, value: int) -> int:
    """Wrap an EDS default into the type's range (e.g. 0xFD for an INTEGER8 is -3)."""
    fmt = STRUCT_FORMAT[data_type]
    if fmt in ("<f", "<d", "<?"):
        return value
    size = struct.calcsize(fmt)
    signed = fmt[1].islower()
    value &= (1 << (8 * size)) - 1
    if signed and value >= 1 << (8 * size - 1):
        value -= 1 << (8 * size)
    return value

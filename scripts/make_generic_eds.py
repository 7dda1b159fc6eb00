"""Regenerate ``can_config/data/generic_cia402.eds``, the project's own CiA 402 EDS.

Run from the repository root: ``python scripts/make_generic_eds.py``. The file describes a
generic servo drive (CiA 402, device type 0x00020192) with the objects the stack uses. Its
default PDO set is the generic CiA 402 one with TPDO2-4 disabled, as many vendor files ship,
so that the driver has to write the mapping it needs at boot.
"""

from __future__ import annotations

from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from can_config.objects import DataType as T

OUT = Path(__file__).resolve().parent.parent / "can_config" / "data" / "generic_cia402.eds"


def var(name: str, index: int, sub: int, dtype: int, access: str, default: object,
        mappable: bool = False) -> ODVariable:
    v = ODVariable(name, index, sub)
    v.data_type = dtype
    v.access_type = access
    v.default = default
    v.default_raw = str(default)
    v.pdo_mappable = mappable
    return v


def record(od: ObjectDictionary, name: str, index: int, members: list[ODVariable]) -> None:
    rec = ODRecord(name, index)
    for m in members:
        rec.add_member(m)
    od.add_object(rec)


def array(od: ObjectDictionary, name: str, index: int, dtype: int, access: str,
          defaults: list[object], count: int | None = None) -> None:
    arr = ODArray(name, index)
    arr.add_member(var("Number of entries", index, 0, T.UNSIGNED8, "rw" if count is not None else "ro",
                       len(defaults) if count is None else count))
    for i, d in enumerate(defaults, start=1):
        arr.add_member(var(f"{name} {i}", index, i, dtype, access, d))
    od.add_object(arr)


def build() -> ObjectDictionary:
    od = ObjectDictionary()
    od.device_information.vendor_name = "rovercan"
    od.device_information.vendor_number = 0x00524F56  # "ROV"
    od.device_information.product_name = "rovercan generic CiA 402 servo"
    od.device_information.product_number = 0x0402
    od.device_information.revision_number = 0x00010000
    od.device_information.order_code = "RC-402"
    od.device_information.allowed_baudrates = {125_000, 250_000, 500_000, 1_000_000}
    od.device_information.simple_boot_up_master = False
    od.device_information.simple_boot_up_slave = True
    od.device_information.granularity = 8
    od.device_information.nr_of_RXPDO = 4
    od.device_information.nr_of_TXPDO = 4
    od.device_information.LSS_supported = False

    add = od.add_object
    add(var("Device type", 0x1000, 0, T.UNSIGNED32, "ro", 0x00020192))
    add(var("Error register", 0x1001, 0, T.UNSIGNED8, "ro", 0, True))
    array(od, "Pre-defined error field", 0x1003, T.UNSIGNED32, "ro", [0] * 8, count=0)  # sub 0: errors recorded
    add(var("COB-ID SYNC", 0x1005, 0, T.UNSIGNED32, "rw", 0x80))
    add(var("Manufacturer device name", 0x1008, 0, T.VISIBLE_STRING, "const",
            "rovercan generic CiA 402 servo"))
    add(var("Manufacturer hardware version", 0x1009, 0, T.VISIBLE_STRING, "const", "1.0"))
    add(var("Manufacturer software version", 0x100A, 0, T.VISIBLE_STRING, "const", "1.0.0"))
    array(od, "Store parameters", 0x1010, T.UNSIGNED32, "rw", [1])  # "save" (0x65766173) stores all
    add(var("COB-ID EMCY", 0x1014, 0, T.UNSIGNED32, "rw", "$NODEID+0x80"))
    array(od, "Consumer heartbeat time", 0x1016, T.UNSIGNED32, "rw", [0])
    add(var("Producer heartbeat time", 0x1017, 0, T.UNSIGNED16, "rw", 0))
    record(od, "Identity object", 0x1018, [
        var("Number of entries", 0x1018, 0, T.UNSIGNED8, "ro", 4),
        var("Vendor-ID", 0x1018, 1, T.UNSIGNED32, "ro", 0x00524F56),
        var("Product code", 0x1018, 2, T.UNSIGNED32, "ro", 0x0402),
        var("Revision number", 0x1018, 3, T.UNSIGNED32, "ro", 0x00010000),
        var("Serial number", 0x1018, 4, T.UNSIGNED32, "ro", 0),
    ])
    rpdo_maps = [[0x60400010], [0x60400010, 0x60600008], [0x60400010, 0x607A0020],
                 [0x60400010, 0x60FF0020]]
    tpdo_maps = [[0x60410010], [0x60410010, 0x60610008], [0x60410010, 0x60640020],
                 [0x60410010, 0x606C0020]]
    for n in range(4):
        record(od, f"RPDO{n + 1} communication parameter", 0x1400 + n, [
            var("Highest sub-index supported", 0x1400 + n, 0, T.UNSIGNED8, "ro", 2),
            var("COB-ID used by RPDO", 0x1400 + n, 1, T.UNSIGNED32, "rw",
                f"$NODEID+0x{0x200 + 0x100 * n:X}"),
            var("Transmission type", 0x1400 + n, 2, T.UNSIGNED8, "rw", 255),
        ])
        record(od, f"RPDO{n + 1} mapping parameter", 0x1600 + n, [
            var("Number of mapped objects", 0x1600 + n, 0, T.UNSIGNED8, "rw", len(rpdo_maps[n])),
            *[var(f"Mapped object {i}", 0x1600 + n, i, T.UNSIGNED32, "rw",
                  rpdo_maps[n][i - 1] if i <= len(rpdo_maps[n]) else 0) for i in range(1, 9)],
        ])
    for n in range(4):
        cob = f"$NODEID+0x{0x180 + 0x100 * n:X}" if n == 0 else f"$NODEID+0x{0x80000180 + 0x100 * n:X}"
        record(od, f"TPDO{n + 1} communication parameter", 0x1800 + n, [
            var("Highest sub-index supported", 0x1800 + n, 0, T.UNSIGNED8, "ro", 5),
            var("COB-ID used by TPDO", 0x1800 + n, 1, T.UNSIGNED32, "rw", cob),
            var("Transmission type", 0x1800 + n, 2, T.UNSIGNED8, "rw", 255),
            var("Inhibit time", 0x1800 + n, 3, T.UNSIGNED16, "rw", 0),
            var("Event timer", 0x1800 + n, 5, T.UNSIGNED16, "rw", 0),
        ])
        record(od, f"TPDO{n + 1} mapping parameter", 0x1A00 + n, [
            var("Number of mapped objects", 0x1A00 + n, 0, T.UNSIGNED8, "rw", len(tpdo_maps[n])),
            *[var(f"Mapped object {i}", 0x1A00 + n, i, T.UNSIGNED32, "rw",
                  tpdo_maps[n][i - 1] if i <= len(tpdo_maps[n]) else 0) for i in range(1, 9)],
        ])
    add(var("Error code", 0x603F, 0, T.UNSIGNED16, "ro", 0, True))
    add(var("Abort connection option code", 0x6007, 0, T.INTEGER16, "rw", 0))
    add(var("Controlword", 0x6040, 0, T.UNSIGNED16, "rw", 0, True))
    add(var("Statusword", 0x6041, 0, T.UNSIGNED16, "ro", 0, True))
    add(var("Quick stop option code", 0x605A, 0, T.INTEGER16, "rw", 2))
    add(var("Modes of operation", 0x6060, 0, T.INTEGER8, "rw", 0, True))
    add(var("Modes of operation display", 0x6061, 0, T.INTEGER8, "ro", 0, True))
    add(var("Position actual value", 0x6064, 0, T.INTEGER32, "ro", 0, True))
    add(var("Following error window", 0x6065, 0, T.UNSIGNED32, "rw", 20000))
    add(var("Following error time out", 0x6066, 0, T.UNSIGNED16, "rw", 100))
    add(var("Velocity actual value", 0x606C, 0, T.INTEGER32, "ro", 0, True))
    add(var("Target torque", 0x6071, 0, T.INTEGER16, "rw", 0, True))
    add(var("Max torque", 0x6072, 0, T.UNSIGNED16, "rw", 3000))
    add(var("Motor rated torque", 0x6076, 0, T.UNSIGNED32, "rw", 1000))
    add(var("Torque actual value", 0x6077, 0, T.INTEGER16, "ro", 0, True))
    add(var("Target position", 0x607A, 0, T.INTEGER32, "rw", 0, True))
    array(od, "Software position limit", 0x607D, T.INTEGER32, "rw", [-2**31, 2**31 - 1])
    record(od, "Position encoder resolution", 0x608F, [  # the simulated motor's 4096-count encoder
        var("Highest sub-index supported", 0x608F, 0, T.UNSIGNED8, "ro", 2),
        var("Encoder increments", 0x608F, 1, T.UNSIGNED32, "rw", 4096),
        var("Motor revolutions", 0x608F, 2, T.UNSIGNED32, "rw", 1),
    ])
    add(var("Max profile velocity", 0x607F, 0, T.UNSIGNED32, "rw", 10_000_000))
    add(var("Profile velocity", 0x6081, 0, T.UNSIGNED32, "rw", 4096, True))
    add(var("Profile acceleration", 0x6083, 0, T.UNSIGNED32, "rw", 16384, True))
    add(var("Profile deceleration", 0x6084, 0, T.UNSIGNED32, "rw", 16384, True))
    add(var("Quick stop deceleration", 0x6085, 0, T.UNSIGNED32, "rw", 65536))
    add(var("Homing method", 0x6098, 0, T.INTEGER8, "rw", 35))
    record(od, "Homing speeds", 0x6099, [
        var("Number of entries", 0x6099, 0, T.UNSIGNED8, "ro", 2),
        var("Speed during search for switch", 0x6099, 1, T.UNSIGNED32, "rw", 1000),
        var("Speed during search for zero", 0x6099, 2, T.UNSIGNED32, "rw", 100),
    ])
    add(var("Homing acceleration", 0x609A, 0, T.UNSIGNED32, "rw", 16384))
    add(var("Following error actual value", 0x60F4, 0, T.INTEGER32, "ro", 0, True))
    add(var("Target velocity", 0x60FF, 0, T.INTEGER32, "rw", 0, True))
    # PP, PV, PT, homing, CSP, CSV, CST
    add(var("Supported drive modes", 0x6502, 0, T.UNSIGNED32, "ro", 0b11_1010_1101))
    return od


def main() -> None:
    canopen.export_od(build(), str(OUT), doc_type="eds")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()

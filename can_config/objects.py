"""Passive CANopen definitions shared by the driver and the emulator.

Only data lives here: object indexes, COB-ID bases, data types, and the code tables of
CiA 301 (SDO abort codes, EMCY error codes) and CiA 402. No behaviour: the driver and the
simulated drive each implement the protocol on their own (see STYLE.md).

Owner: none; values only.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Final

from canopen.objectdictionary import datatypes


class OD(IntEnum):
    """Object dictionary indexes used by the stack (CiA 301 and CiA 402)."""

    DEVICE_TYPE = 0x1000
    ERROR_REGISTER = 0x1001
    PREDEFINED_ERROR_FIELD = 0x1003
    COB_ID_SYNC = 0x1005
    DEVICE_NAME = 0x1008
    HARDWARE_VERSION = 0x1009
    SOFTWARE_VERSION = 0x100A
    STORE_PARAMETERS = 0x1010
    COB_ID_EMCY = 0x1014
    GUARD_TIME = 0x100C
    LIFE_TIME_FACTOR = 0x100D
    CONSUMER_HEARTBEAT_TIME = 0x1016
    PRODUCER_HEARTBEAT_TIME = 0x1017
    IDENTITY = 0x1018
    VERIFY_CONFIGURATION = 0x1020
    ERROR_BEHAVIOUR = 0x1029
    RPDO_COMM = 0x1400
    RPDO_MAP = 0x1600
    TPDO_COMM = 0x1800
    TPDO_MAP = 0x1A00
    ABORT_CONNECTION_OPTION = 0x6007
    ERROR_CODE = 0x603F
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    QUICK_STOP_OPTION = 0x605A
    MODES_OF_OPERATION = 0x6060
    MODES_OF_OPERATION_DISPLAY = 0x6061
    POSITION_ACTUAL = 0x6064
    FOLLOWING_ERROR_WINDOW = 0x6065
    FOLLOWING_ERROR_TIMEOUT = 0x6066
    VELOCITY_ACTUAL = 0x606C
    TARGET_TORQUE = 0x6071
    MAX_TORQUE = 0x6072
    RATED_TORQUE = 0x6076
    TORQUE_ACTUAL = 0x6077
    TARGET_POSITION = 0x607A
    HOME_OFFSET = 0x607C
    SOFTWARE_POSITION_LIMIT = 0x607D
    POLARITY = 0x607E
    MAX_PROFILE_VELOCITY = 0x607F
    PROFILE_VELOCITY = 0x6081
    PROFILE_ACCELERATION = 0x6083
    PROFILE_DECELERATION = 0x6084
    QUICK_STOP_DECELERATION = 0x6085
    POSITION_FACTOR = 0x6093
    POSITION_ENCODER_RESOLUTION = 0x608F
    GEAR_RATIO = 0x6091
    FEED_CONSTANT = 0x6092
    HOMING_METHOD = 0x6098
    HOMING_SPEEDS = 0x6099
    HOMING_ACCELERATION = 0x609A
    SI_UNIT_POSITION = 0x60A8
    SI_UNIT_VELOCITY = 0x60A9
    SI_UNIT_ACCELERATION = 0x60AA
    POSITION_OFFSET = 0x60B0  # CSP: added to the target position
    INTERPOLATION_DATA = 0x60C1  # record; sub 1: the interpolated position set-point
    VELOCITY_OFFSET = 0x60B1  # CSV: added to the target velocity
    TORQUE_OFFSET = 0x60B2  # CST: added to the target torque
    FOLLOWING_ERROR_ACTUAL = 0x60F4
    TARGET_VELOCITY = 0x60FF
    SUPPORTED_DRIVE_MODES = 0x6502


#: EMCY / error history code of a heartbeat consumer or life guard that lost its producer (CiA 301):
#: what a drive reports when it stopped itself because the host fell silent.
EMCY_HEARTBEAT_LOST = 0x8130


class FunctionCode:
    """COB-ID bases of the CANopen predefined connection set (add the node id). Plain constants,
    not an enum: EMCY and SYNC share 0x080 (SYNC alone, EMCY with a node id), which an IntEnum
    would make one member."""

    NMT: Final = 0x000
    SYNC: Final = 0x080
    EMCY: Final = 0x080
    TIME: Final = 0x100
    TPDO1: Final = 0x180
    RPDO1: Final = 0x200
    TPDO2: Final = 0x280
    RPDO2: Final = 0x300
    TPDO3: Final = 0x380
    RPDO3: Final = 0x400
    TPDO4: Final = 0x480
    RPDO4: Final = 0x500
    SDO_TX: Final = 0x580
    SDO_RX: Final = 0x600
    HEARTBEAT: Final = 0x700


TPDO_BASES = (0x180, 0x280, 0x380, 0x480)
RPDO_BASES = (0x200, 0x300, 0x400, 0x500)
PDO_COB_ID_INVALID = 0x8000_0000  # bit 31 of a PDO COB-ID: PDO does not exist / is disabled
PDO_COB_ID_NO_RTR = 0x4000_0000


class NmtCommand(IntEnum):
    """NMT command specifiers (byte 0 of a COB-ID 0x000 frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PREOPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as carried in a heartbeat frame."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


#: The CiA 301 data type codes as they appear in an EDS (``DataType.UNSIGNED32``): canopen's own
#: table, the one its object dictionary and SDO client read them by.
DataType = datatypes


#: Little-endian struct formats of the fixed-size data types.
STRUCT_FORMAT: dict[int, str] = {
    DataType.BOOLEAN: "<?",
    DataType.INTEGER8: "<b",
    DataType.INTEGER16: "<h",
    DataType.INTEGER32: "<i",
    DataType.UNSIGNED8: "<B",
    DataType.UNSIGNED16: "<H",
    DataType.UNSIGNED32: "<I",
    DataType.REAL32: "<f",
    DataType.REAL64: "<d",
    DataType.INTEGER64: "<q",
    DataType.UNSIGNED64: "<Q",
}

#: Size in bytes of each fixed-size data type.
DATA_TYPE_SIZE: dict[int, int] = {code: struct.calcsize(fmt) for code, fmt in STRUCT_FORMAT.items()}
DATA_TYPE_SIZE[DataType.INTEGER24] = 3
DATA_TYPE_SIZE[DataType.UNSIGNED24] = 3


class OperationMode(IntEnum):
    """CiA 402 modes of operation (0x6060 / 0x6061)."""

    NO_MODE = 0
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


#: Bit of 0x6502 (supported drive modes) for each mode: CiA 402 gives mode n bit n - 1.
SUPPORTED_MODE_BIT: dict[OperationMode, int] = {
    mode: mode - 1 for mode in OperationMode if mode is not OperationMode.NO_MODE}

#: CiA 402 device profile number in the low 16 bits of 0x1000.
CIA402_PROFILE = 402


class Cia402State(IntEnum):
    """The names of the CiA 402 power drive states (figure 'state machine'), a passive
    definition both sides use. How a statusword codes them is not here: the driver
    (motor_driver/protocol/cia402.py) and the simulator (virtual_can/sim/drive/model.py) each read it from
    the standard on their own, so that a misreading is not baked into both. UNKNOWN is no
    drive's state: what a master makes of a statusword that codes none of them."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7
    UNKNOWN = 8


#: SDO abort codes (CiA 301, 7.2.4.3.17) and their meaning.
SDO_ABORT_TEXT: dict[int, str] = {
    0x0503_0000: "toggle bit not alternated",
    0x0504_0000: "SDO protocol timed out",
    0x0504_0001: "client/server command specifier not valid or unknown",
    0x0504_0002: "invalid block size",
    0x0504_0003: "invalid sequence number",
    0x0504_0004: "CRC error",
    0x0504_0005: "out of memory",
    0x0601_0000: "unsupported access to an object",
    0x0601_0001: "attempt to read a write only object",
    0x0601_0002: "attempt to write a read only object",
    0x0602_0000: "object does not exist in the object dictionary",
    0x0604_0041: "object cannot be mapped to the PDO",
    0x0604_0042: "the number and length of the objects to be mapped would exceed PDO length",
    0x0604_0043: "general parameter incompatibility",
    0x0604_0047: "general internal incompatibility in the device",
    0x0606_0000: "access failed due to a hardware error",
    0x0607_0010: "data type does not match, length of service parameter does not match",
    0x0607_0012: "data type does not match, length of service parameter too high",
    0x0607_0013: "data type does not match, length of service parameter too low",
    0x0609_0011: "sub-index does not exist",
    0x0609_0030: "invalid value for parameter (download only)",
    0x0609_0031: "value of parameter written too high (download only)",
    0x0609_0032: "value of parameter written too low (download only)",
    0x0609_0036: "maximum value is less than minimum value",
    0x060A_0023: "resource not available: SDO connection",
    0x0800_0000: "general error",
    0x0800_0020: "data cannot be transferred or stored to the application",
    0x0800_0021: "data cannot be transferred or stored because of local control",
    0x0800_0022: "data cannot be transferred or stored because of the present device state",
    0x0800_0023: "object dictionary dynamic generation failed or no object dictionary present",
    0x0800_0024: "no data available",
}


def sdo_abort_text(code: int) -> str:
    """The meaning of an SDO abort code, or a note that the code is vendor specific."""
    return SDO_ABORT_TEXT.get(code, "unknown or manufacturer-specific abort code")


#: EMCY error codes (CiA 301 table 21 and CiA 402 annex), most specific first by lookup.
EMCY_TEXT: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x2310: "continuous over-current",
    0x2320: "short circuit / earth leakage",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3200: "voltage inside the device",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3300: "output voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5000: "device hardware",
    0x5200: "device hardware: control",
    0x5201: "device hardware: control, measurement circuit",
    0x5400: "device hardware: power section",
    0x5441: "safe torque off (STO) active",
    0x6000: "device software",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x7000: "additional modules",
    0x7300: "sensor",
    0x7305: "incremental sensor 1 fault",
    0x7500: "communication",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8300: "torque control",
    0x8311: "excess torque",
    0x8400: "velocity speed controller",
    0x8500: "position controller",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}


def emcy_text(code: int) -> str:
    """A human sentence for an EMCY error code: the most specific entry of the tables."""
    for mask in (0xFFFF, 0xFFF0, 0xFF00, 0xF000):
        text = EMCY_TEXT.get(code & mask)
        if text is not None:
            return text
    return "unknown error code"

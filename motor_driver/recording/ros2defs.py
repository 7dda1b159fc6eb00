"""The ROS 2 message definitions the project writes to MCAP and serves to Foxglove (pure, no rclpy).

An MCAP file of the ROS 2 profile carries, for each channel, its type's definition as ``ros2 bag``
writes it (``ros2msg``): the type's own text, then each type it uses after a line of ``=`` and
``MSG: pkg/Type``. :func:`schema_text` builds that from :data:`DEFINITIONS`, which holds the
standard types used (as ROS 2 Jazzy defines them) and this project's own, whose text must equal
``ros/rovercan_msgs/msg/*.msg`` (tests/test_mcap.py holds them in step).
"""

from __future__ import annotations

import re
from functools import cache

#: The raw frames' type, the drives' joint states, the per-drive state and the diagnostics.
CAN_FRAME = "rovercan_msgs/msg/CanFrame"
DRIVE_STATUS = "rovercan_msgs/msg/DriveStatus"
JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

_SEPARATOR = "=" * 80

DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": """\
int32 sec
uint32 nanosec
""",
    "std_msgs/msg/Header": """\
builtin_interfaces/Time stamp
string frame_id
""",
    "sensor_msgs/msg/JointState": """\
std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
""",
    "diagnostic_msgs/msg/KeyValue": """\
string key
string value
""",
    "diagnostic_msgs/msg/DiagnosticStatus": """\
byte OK=0
byte WARN=1
byte ERROR=2
byte STALE=3
byte level
string name
string message
string hardware_id
KeyValue[] values
""",
    "diagnostic_msgs/msg/DiagnosticArray": """\
std_msgs/Header header
DiagnosticStatus[] status
""",
    "rovercan_msgs/msg/MotorState": """\
# State of one CiA 402 drive, as the driver last saw it from its PDOs.
# The first two fields are the team's original message and keep their names and units.

float32 angle            # joint angle [deg]
float32 torque           # joint torque [Nm]

std_msgs/Header header   # stamp: when the PDOs carrying this state arrived
string name              # joint name from the configuration
float32 velocity         # joint velocity [deg/s]
string state             # CiA 402 state, e.g. "OPERATION_ENABLED", "FAULT"
bool enabled             # true only in Operation Enabled
bool fault               # true in Fault / Fault Reaction Active, or when the drive is lost
uint16 error_code        # last EMCY error code (0 = none)
bool stale               # no PDO for stale_after_syncs SYNC periods: angle, velocity, torque are NaN
float32 data_age         # seconds since the last PDO arrived
""",
    "rovercan_msgs/msg/CanFrame": """\
# One CAN frame as it was on a bus: `rovercan record FILE.mcap`, `rovercan decode FILE -o OUT.mcap`,
# the flight recorder's incident .mcap and the live view (`rovercan monitor --foxglove PORT`).

std_msgs/Header header   # stamp: the frame's time on the bus; frame_id: the bus (config bus name, or channel)
uint32 id                # arbitration id (11 bits, or 29 when is_extended)
bool is_extended         # a 29-bit id
bool is_rtr              # a remote transmission request
bool is_error            # an error frame (id and data carry the error class)
uint8 dlc                # data length code
uint8[] data             # the data bytes
""",
    "rovercan_msgs/msg/DriveStatus": """\
# One CiA 402 drive as decoded from its frames on the bus, by its EDS and the driver's PDO map:
# `rovercan record FILE.mcap --config C`, `rovercan decode FILE --config C -o OUT.mcap`, the flight
# recorder's incident .mcap and the live view. Sent only when frames of the drive came: a lost or
# stale drive has none, never a repeated one.

rovercan_msgs/MotorState motor  # as the driver publishes it; header.stamp: the frames' time; NaN torque: not mapped
string bus                      # the config bus the drive is on
uint8 node_id                   # its CANopen node id
uint16 statusword               # 0x6041
uint16 controlword              # 0x6040 as last sent to it in an RPDO (0: none seen)
int8 mode                       # modes of operation display (0x6061)
string mode_name                # e.g. "CYCLIC_SYNC_POSITION"
string nmt                      # NMT state of its last heartbeat ("" before one)
uint16 emcy_code                # its last EMCY error code (0: none, or reset)
string emcy_text                # what that code means
""",

}

_TYPE = re.compile(r"^\s*([A-Za-z][\w/]*)(?:\[\d*\])?\s+\w+\s*(?:#.*)?$")


def _uses(name: str) -> list[str]:
    """The message types ``name``'s fields use, as full names, in the order they appear."""
    package = name.split("/", maxsplit=1)[0]
    found: list[str] = []
    for line in DEFINITIONS[name].splitlines():
        match = _TYPE.match(line)
        if not match or "=" in line:
            continue
        parts = match.group(1).split("/")
        if len(parts) == 1 and parts[0][0].isupper():
            parts = [package, parts[0]]  # a type of the same package
        if len(parts) == 2:
            full = f"{parts[0]}/msg/{parts[1]}"
            if full in DEFINITIONS and full not in found:
                found.append(full)
    return found


@cache
def schema_text(name: str) -> str:
    """``name``'s definition with every type it uses, as an MCAP ``ros2msg`` schema."""
    order: list[str] = []
    pending = _uses(name)
    while pending:
        dep = pending.pop(0)
        if dep not in order:
            order.append(dep)
            pending += _uses(dep)
    parts = [DEFINITIONS[name].rstrip("\n")]
    for dep in order:
        package, _, type_name = dep.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {package}/{type_name}\n{DEFINITIONS[dep].rstrip(chr(10))}")
    return "\n".join(parts) + "\n"

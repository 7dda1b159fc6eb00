"""Every ROS parameter of the rovercan nodes, defined in one place with a description and a range,
and which node declares which (:data:`NODES`).

Values come from ``config/rovercan.params.yaml`` (``--ros-args --params-file``: a section per node
name of :data:`NODES`) or ``-p``. A parameter read once at start (the config, the executor, the
scheduling, what the node is made of) is declared read-only: a set at run time is refused, the
reason naming what to do (restart with the new value); the others take effect when set.

Each parameter is declared once, by the code that reads it: the process set-up
(:func:`nodes.assembly.set_up`) declares ``executor`` and ``realtime_priority`` on the entry
point's own node, the entry point ``config``, each node the rest. docs/ros.md's table is
:func:`table` (``python -m nodes.process.params``; tests/test_params_file.py holds the two in step).

Owner: none; values only, read where a node declares its parameters.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node

from can_config.errors import ConfigError
from can_config.realtime import DRIVER_PRIORITY


@dataclass(frozen=True)
class Param:
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    at_start: bool = True  #: read once at start: read-only (a set at run time is refused)


PARAMS: dict[str, Param] = {
    "config": Param("", "rover config YAML (buses, drives, drive system); empty: $ROVERCAN_CONFIG where set, else"
                       " the embedded default"),
    "sim": Param(False, "the launch started the simulator for this process (sim:=true): its config is never"
                        " $ROVERCAN_CONFIG (empty: the embedded default), and a bus that is not the simulator's"
                        " (not socketcand) is refused, nothing opened"),
    "executor": Param("events", "hot-path executor: events (rclpy's EventsExecutor, measured fastest) or single"),
    "arm": Param(False, "enable every drive at start (rover_lifecycle: at activate); off by default: arming is an"
                        " explicit act"),
    "drive_system": Param(True, "run the config's drive_system (/cmd_vel -> wheels -> /odom); false: leave the"
                                " wheels to another (ros2_control's diff_drive_controller)"),
    "default_joint": Param("", "joint that /motor_degree_cmd moves and /motor_state reports (the team's demo topics);"
                               " empty: none (the topics are not served)"),
    "joint": Param("", "motor_controller: the one joint it serves, on /motor_degree_cmd and /motor_state too"),
    "state_rate_hz": Param(50.0, "rate of MotorState and /joint_states; set at run time: takes effect unless the"
                                 " drive system's control loop shares the timer", 1.0, 500.0, at_start=False),
    "diagnostics_rate_hz": Param(1.0, "rate of /diagnostics", 0.1, 10.0, at_start=False),
    "state_qos_depth": Param(10, "keep-last depth of the reliable state topics (MotorState, /joint_states, /odom),"
                                 " 1 to 1000"),
    "autostart": Param(False, "rover_lifecycle: configure and activate at start (the demo); off: a lifecycle"
                              " manager drives the transitions"),
    "bond_heartbeat_period": Param(0.1, "rover_lifecycle: seconds between two heartbeats of its bond with a"
                                        " lifecycle manager (Nav2's; made at activate, as Nav2's managed nodes"
                                        " make it); 0: no bond", 0.0, 10.0),
    "realtime_priority": Param(DRIVER_PRIORITY, "SCHED_FIFO priority of the driver process's threads (commands, supervisor, stops,"
                                   " DDS, each bus's receive thread), 1 to 99, where the OS allows it (CAP_SYS_NICE, an rtprio"
                                   " limit; else ordinary, said once); 0: ordinary scheduling"),
    "odom_rate_hz": Param(50.0, "rate of the drive system's control loop and at most of /odom (a measured /odom"
                                " comes only with new samples of both sides)", 1.0, 200.0),
    "odom_frame": Param("odom", "frame_id of /odom"),
    "base_frame": Param("base_link", "child_frame_id of /odom"),
    "publish_tf": Param(True, "drive_system: publish /tf odom -> base_link from the wheel odometry; false: another"
                              " node fuses odometry (robot_localization) and owns that transform"),
    "period_s": Param(0.1, "motor_degree: seconds between two commands", 0.001, 3600.0),
    "step_deg": Param(0.1, "motor_degree: degrees added to the command each period (modulo 360), in tenths of a"
                           " degree (another value is rounded, and said)", -360.0, 360.0),
    "start_deg": Param(0.0, "motor_degree: the command before the first step, degrees, in tenths (as step_deg)",
                       -360.0, 360.0),
}

#: Read by the process set-up (:func:`nodes.assembly.set_up`), on the entry point's own node.
PROCESS = ("executor", "realtime_priority")
#: The driver node's own (``rovercan_driver``; the lifecycle's driver node declares these alone).
DRIVER = ("arm", "drive_system", "default_joint", "state_rate_hz", "diagnostics_rate_hz", "state_qos_depth")
#: The driver node restricted to one joint (``motor_controller``): ``joint`` is its demo joint too.
ONE_JOINT = ("joint", "arm", "state_rate_hz", "diagnostics_rate_hz", "state_qos_depth")
#: What each node of an entry point declares, by the node's name: the sections of
#: config/rovercan.params.yaml. ``rovercan_driver`` as ``rover_driver`` makes it; in
#: ``rover_lifecycle``'s process the node of that name has :data:`DRIVER` only (the process's
#: ``config``, ``executor`` and ``realtime_priority`` are ``rovercan_lifecycle``'s).
NODES: dict[str, tuple[str, ...]] = {
    "rovercan_driver": ("config", "sim", *PROCESS, *DRIVER),
    "motor_controller": ("config", "sim", *PROCESS, *ONE_JOINT),
    "rovercan_lifecycle": ("config", "sim", *PROCESS, "autostart", "bond_heartbeat_period"),
    "drive_system": ("odom_rate_hz", "odom_frame", "base_frame", "state_qos_depth", "publish_tf"),
    "motor_degree": ("period_s", "step_deg", "start_deg"),
}


#: Why a parameter read once at start refuses a set at run time (rclpy says "read-only" and this).
AT_START = "read once at start: restart the node with the new value (-p NAME:=VALUE or --params-file)"


def declare(node: Node, *names: str) -> None:
    for name in names:
        spec = PARAMS[name]
        descriptor = ParameterDescriptor(description=spec.description, read_only=spec.at_start)
        if spec.at_start:
            descriptor.additional_constraints = AT_START
        if spec.low is not None and spec.high is not None:
            descriptor.floating_point_range = [FloatingPointRange(from_value=spec.low, to_value=spec.high)]
        try:
            node.declare_parameter(name, spec.default, descriptor)
        except (InvalidParameterTypeException, InvalidParameterValueException) as err:  # -p name:=a bad value
            kind = type(spec.default).__name__
            span = f" from {spec.low:g} to {spec.high:g}" if spec.low is not None and spec.high is not None else ""
            example = str(spec.default).lower() if isinstance(spec.default, bool) else repr(spec.default)
            raise ConfigError(f"parameter {name}: {err}; expected a {kind}{span} (the default: -p {name}:={example});"
                              " a typed launch or YAML value is taken as given (1 is an integer, 1.0 a float,"
                              " true a bool)") from None


def qos_depth(node: Node) -> int:
    """``state_qos_depth``, checked: a whole number from 1 to 1000."""
    value = node.get_parameter("state_qos_depth").value
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 1000:
        raise ConfigError(f"parameter state_qos_depth = {value!r}: expected a whole number from 1 to 1000")
    return int(value)


BEGIN = "<!-- parameters: generated by python -m nodes.process.params; do not edit by hand -->"
END = "<!-- end of parameters -->"


def table() -> str:
    """docs/ros.md's parameter table: every parameter, the nodes that declare it, its default,
    range, when it is read and what it does."""
    out = [BEGIN, "", "| parameter | nodes | default | range | read | what |", "|---|---|---|---|---|---|"]
    for name, spec in PARAMS.items():
        nodes = ", ".join(f"`{node}`" for node, names in NODES.items() if name in names)
        span = f"{spec.low:g} to {spec.high:g}" if spec.low is not None and spec.high is not None else ""
        default = f"`{spec.default!r}`" if isinstance(spec.default, str) else f"`{str(spec.default).lower()}`"
        read = "at start" if spec.at_start else "when set"
        out.append(f"| `{name}` | {nodes} | {default} | {span} | {read} | {spec.description} |")
    out += ["", END]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    sys.stdout.write(table())

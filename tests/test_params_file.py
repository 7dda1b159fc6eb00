"""The ROS parameters are declared once each, where they are read, and written down from there:
config/rovercan.params.yaml has a section for every node name an entry point makes, each listing
exactly what that node declares (its defaults); a copy of the file with other values, loaded into
each entry point as ``--params-file`` (real rclpy nodes, made by the entry point's own code), sets
every value it names; docs/ros.md's table is the one generated from the declarations."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from can_config import load_config
from can_config.errors import ConfigError
from virtual_can.service import SimService

from .conftest import REPO
from .test_mcap import ROVER, rover_on_port

rclpy = pytest.importorskip("rclpy")

if True:  # ROS present
    from rclpy.parameter import Parameter

    from nodes.assembly import assemble
    from nodes.motor_degree import MotorDegreeNode
    from nodes.process.params import BEGIN, DRIVER, END, NODES, PARAMS, declare, table
    from nodes.rover_lifecycle import DriveLifecycleNode

PARAMS_FILE = REPO / "config" / "rovercan.params.yaml"
DOCS = REPO / "docs" / "ros.md"
JOINT = "wheel_front_left"


def shipped() -> dict[str, dict[str, Any]]:
    data = yaml.safe_load(PARAMS_FILE.read_text())
    return {node: section["ros__parameters"] for node, section in data.items()}


def test_the_docs_hold_the_generated_table() -> None:
    text = DOCS.read_text()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    assert text[start:end] + "\n" == table(), "docs/ros.md is stale: python -m nodes.process.params"


@pytest.mark.parametrize(("arg", "said"), [
    ("arm:=1", "parameter arm: .*expecting type 'BOOL'.*; expected a bool \\(the default: -p arm:=false\\)"),
    ("state_rate_hz:=1000.0", "parameter state_rate_hz: .*out of range.*; expected a float from 1 to 500 \\(the"
                              " default: -p state_rate_hz:=50.0\\)")])
def test_a_parameter_of_the_wrong_type_or_range_is_a_config_error_naming_it(arg: str, said: str) -> None:
    """rclpy's own exception (a bug's trace, ERROR processing in the lifecycle node) becomes the
    driver's ConfigError: the parameter, what was wrong, what it takes and how to give it."""
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-p", arg])
    node = rclpy.create_node("declares", context=context)
    try:
        with pytest.raises(ConfigError, match=said):
            declare(node, arg.split(":=", maxsplit=1)[0])
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_the_file_has_a_section_per_node_with_what_it_declares() -> None:
    sections = shipped()
    assert set(sections) == set(NODES)
    for node, names in NODES.items():
        assert set(sections[node]) == set(names), node
        assert {k: v for k, v in sections[node].items()} == {k: PARAMS[k].default for k in names}, node


def variant(config: Path) -> dict[str, dict[str, Any]]:
    """The shipped file with every value changed (but drive_system, which must stay on for the
    drive system's node to exist): a node that ignored its section would keep the old value."""
    special = {"config": str(config), "executor": "single", "realtime_priority": 0, "joint": JOINT,
               "default_joint": JOINT, "odom_frame": "odom_test", "base_frame": "base_test", "drive_system": True}
    out = copy.deepcopy(shipped())
    for values in out.values():
        for name, value in values.items():
            if name in special:
                values[name] = special[name]
            elif isinstance(value, bool):
                values[name] = not value
            elif isinstance(value, int):
                values[name] = value // 2
            else:
                values[name] = value / 2 if value else 0.5
    for node, values in out.items():
        assert all(v != shipped()[node][k] for k, v in values.items() if k != "drive_system"), node
    return out


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[dict[str, dict[str, Any]], Any]]:
    """The rover's simulated drives, a config file for them, the variant params file loaded into
    a fresh rclpy context as an entry point's ``--ros-args --params-file`` is."""
    with SimService.from_config(load_config(ROVER), port=0) as sim:
        values = variant(rover_on_port(tmp_path, sim.port))
        path = tmp_path / "params.yaml"
        path.write_text(yaml.safe_dump({node: {"ros__parameters": v} for node, v in values.items()}))
        context = rclpy.Context()
        rclpy.init(args=["--ros-args", "--params-file", str(path)], context=context)
        try:
            yield values, context
        finally:
            rclpy.try_shutdown(context=context)


#: What rclpy declares on every node.
RCLPY_OWN = {"use_sim_time", "start_type_description_service"}


def declared(node: Any) -> dict[str, Any]:
    return {name: p.value for name, p in node.get_parameters_by_prefix("").items() if name not in RCLPY_OWN}


def check(nodes: list[Any], values: dict[str, dict[str, Any]], expected: dict[str, tuple[str, ...]]) -> None:
    """Each node named in ``expected`` declares exactly those parameters, valued as the file says."""
    by_name = {node.get_name(): node for node in nodes}
    assert set(expected) <= set(by_name), sorted(by_name)
    for name, names in expected.items():
        got = declared(by_name[name])
        assert set(got) == set(names), name
        assert got == {k: values[name][k] for k in names}, name


@pytest.mark.parametrize(("name", "one_joint"), [("rovercan_driver", False), ("motor_controller", True)])
def test_the_driver_entry_points_take_the_file(rig: tuple[dict[str, dict[str, Any]], Any], name: str,
                                               one_joint: bool) -> None:
    values, context = rig
    assembly = assemble(name, one_joint=one_joint, context=context)  # rover_driver's and motor_controller's run()
    try:
        check(assembly.nodes, values, {name: NODES[name], **({} if one_joint else {"drive_system": NODES["drive_system"]})})
        assert type(assembly.hot).__name__ == "SingleThreadedExecutor"  # executor: single, from the file
        for param, value in (("config", "/etc/shadow"), ("executor", "events"), ("realtime_priority", 20)):
            result = assembly.nodes[0].set_parameters([Parameter(param, value=value)])[0]
            assert not result.successful and "read-only" in result.reason, (param, result)  # read once, at start
    finally:
        assembly.close()


def test_the_lifecycle_entry_point_takes_the_file(rig: tuple[dict[str, dict[str, Any]], Any]) -> None:
    values, context = rig
    node = DriveLifecycleNode(context=context)  # as main() makes it: the process set-up from its parameters
    try:
        check([node], values, {"rovercan_lifecycle": NODES["rovercan_lifecycle"]})
        assert type(node.hot).__name__ == "SingleThreadedExecutor"
        node.trigger_configure()  # the driver of the file's config, booted; its nodes made
        assert node.assembly is not None, "configure failed"
        check(node.assembly.nodes, values, {"rovercan_driver": DRIVER, "drive_system": NODES["drive_system"]})
    finally:
        node.release()
        node.destroy_node()


def test_the_degree_publisher_takes_the_file(rig: tuple[dict[str, dict[str, Any]], Any]) -> None:
    values, context = rig
    node = MotorDegreeNode(context=context)
    try:
        check([node], values, {"motor_degree": NODES["motor_degree"]})
    finally:
        node.destroy_node()


@pytest.mark.parametrize(("sim", "given", "opens"), [(True, False, "socketcand"), (False, False, "socketcan"),
                                                     (True, True, None), (True, "remote", None)])
def test_a_launch_with_the_simulator_never_takes_the_rover_s_real_buses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                        sim: bool, given: bool | str,
                                                                        opens: str | None) -> None:
    """``sim:=true`` (the launch starts the simulator beside the driver): $ROVERCAN_CONFIG, which names
    the deployed rover's real buses, is not read (the simulator serves the embedded default), and a
    config given with a kernel bus is refused before anything opens; without sim it is the rover's.
    Every launch node that takes the launch's config takes its sim too."""
    import xml.etree.ElementTree as ET

    from can_config import DEFAULT_CONFIG
    from nodes.assembly import config_of

    real = tmp_path / "real.yaml"
    real.write_text(ROVER.read_text().replace("interface: socketcand", "interface: socketcan"))
    remote = tmp_path / "remote.yaml"  # a real socketcand daemon beside the rover's drives
    remote.write_text(ROVER.read_text().replace("host: 127.0.0.1", "host: 192.168.1.20"))
    monkeypatch.setenv("ROVERCAN_CONFIG", str(real))
    given_path = remote if given == "remote" else real
    args = ["-p", f"sim:={str(sim).lower()}", *(["-p", f"config:={given_path}"] if given else [])]
    context = rclpy.Context()
    rclpy.init(args=["--ros-args", *args], context=context)
    node = rclpy.create_node("rovercan_driver", context=context)
    try:
        declare(node, "config", "sim")
        if opens is None:
            said = r"can0 \(socketcand can0 on 192\.168\.1\.20\)" if given == "remote" else r"can0 \(socketcan can0\)"
            with pytest.raises(ConfigError, match=rf"sim:=true.*{said}.*would be a real bus"):
                config_of(node)
        else:
            config = config_of(node)
            assert {b.interface for b in config.buses} == {opens}
            assert config == load_config(DEFAULT_CONFIG if sim else real)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    for launch in sorted((REPO / "ros" / "rovercan_bringup" / "launch").glob("*.xml")):
        for element in ET.parse(launch).getroot().iter("node"):
            params = {p.get("name"): p.get("value") for p in element.iter("param")}
            assert "config" not in params or params.get("sim") == "$(var sim)", (launch.name, element.get("exec"))

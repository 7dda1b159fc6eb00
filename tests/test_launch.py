"""The XML launch file: it parses, names only executables that exist, and `rovercan launch`
runs the same graph (separate processes) where the ros2 CLI is absent."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from can_config import ConfigError
from rovercan.launch import EXECUTABLES, parse_launch

from .conftest import REPO, requires_ros, ros_probe
from .test_sim_cli import free_port

LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "motor_launch.xml"
BRINGUP = REPO / "ros" / "rovercan_bringup"


def test_launch_file_names_only_existing_executables() -> None:
    processes = parse_launch(LAUNCH, {"sim": "true"})
    names = [p.name for p in processes]
    assert names[1:] == ["motor_controller", "motor_degree"]
    for exe in EXECUTABLES:
        script = BRINGUP / "scripts" / exe
        assert script.is_file() and os.access(script, os.X_OK)
        assert f"from nodes.{exe} import main" in script.read_text()
        assert (REPO / "nodes" / f"{exe}.py").is_file()
    assert "scripts/motor_controller scripts/motor_degree scripts/rover_driver" in (BRINGUP / "CMakeLists.txt").read_text()
    rover = parse_launch(BRINGUP / "launch" / "rover_launch.xml", {"config": "config/rover.yaml", "sim": "true"})
    assert [p.name for p in rover] == ["python", "rover_driver"]  # the executable: no name renames its nodes
    assert "nodes.rover_driver" in rover[1].argv and "config:=config/rover.yaml" in rover[1].argv


def test_unknown_launch_argument_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"unknown launch argument\(s\) \['speed'\]"):
        parse_launch(LAUNCH, {"speed": "1"})


@requires_ros
def test_rovercan_launch_runs_the_graph(tmp_path: Path) -> None:
    """The launched graph works end to end: motor_degree -> DDS -> motor_controller -> CANopen.
    Observed on the bus (RPDO set-points that follow the degree ramp), so the check does not
    depend on DDS discovery between the test process and the launched ones."""
    import can

    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                      "drives:\n  - {name: motor, node_id: 1, counts_per_rev: 4096}\n")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), "sim:=true", "arm:=true",
                             f"config:={config}", "--duration", "60"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    targets: list[int] = []
    try:
        listener = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)  # retries 10 s
        try:
            deadline = time.monotonic() + 40.0  # three Python processes start on two cores
            while time.monotonic() < deadline and len(targets) < 5:
                msg = listener.recv(0.5)
                if msg is not None and msg.arbitration_id == 0x301 and msg.data[0] & 0x10:  # new set-point
                    targets.append(int.from_bytes(msg.data[2:6], "little", signed=True))
        finally:
            listener.shutdown()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert len(targets) >= 5, f"no set-points from the launched graph: {out[-3000:]}"
    assert targets == sorted(targets) and targets[-1] > targets[0]  # following the +0.1 deg ramp
    assert proc.returncode == 0, out[-3000:]


STOPPER = """
import signal, sys, time
name, log = sys.argv[1], sys.argv[2]
def note(what):
    with open(log, "a") as f:
        f.write(f"{name} {what}\\n")
def on_int(signum, frame):
    note("stopping")
    time.sleep(0.5)  # a safe stop that needs the processes started before it
    note("stopped")
    sys.exit(0)
signal.signal(signal.SIGINT, on_int)
note("ready")
while True:
    time.sleep(0.05)
"""


def write_launch(tmp_path: Path) -> Path:
    (tmp_path / "stopper.py").write_text(STOPPER)
    launch = tmp_path / "two.xml"
    launch.write_text('<launch>\n  <arg name="py" default="python3"/>\n  <arg name="log" default="log.txt"/>\n'
                      '  <executable cmd="$(var py) stopper.py bus $(var log)"/>\n'
                      '  <executable cmd="$(var py) stopper.py driver $(var log)"/>\n</launch>\n')
    return launch


def test_a_launch_value_is_one_argument_whatever_it_holds(tmp_path: Path) -> None:
    hostile = "c.yaml' --host 0.0.0.0 --allow-remote --port '1234"
    processes = parse_launch(write_launch(tmp_path), {"log": hostile})
    assert processes[0].argv[-1] == hostile and "--allow-remote" not in processes[0].argv
    sim = parse_launch(REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml",
                       {"config": hostile, "sim": "true"})[0]
    assert hostile in sim.argv and "--allow-remote" not in sim.argv


def run_launcher(tmp_path: Path, launch: Path, log: Path) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(launch), f"py:={sys.executable}",
                             f"log:={log}"], cwd=tmp_path, start_new_session=True,
                            env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


@pytest.mark.parametrize("how", ["ctrl_c", "sigterm"])
def test_a_stop_reaches_the_processes_in_reverse_order_each_before_the_next(tmp_path: Path, how: str) -> None:
    """A terminal's Ctrl+C goes to the whole foreground process group; `docker stop` sends SIGTERM
    to the container's PID 1 alone (deploy/entrypoint.sh execs the launcher). Either way the
    launched processes get SIGINT (the driver's safe stop) from the runner only, last started
    first, each gone before the next is signalled: the driver's safe stop still finds the bus (the
    simulator) there."""
    import signal

    log = tmp_path / "log.txt"
    runner = run_launcher(tmp_path, write_launch(tmp_path), log)
    try:
        deadline = time.monotonic() + 20
        while (not log.exists() or log.read_text().count("ready") < 2) and time.monotonic() < deadline:
            time.sleep(0.05)
        if how == "ctrl_c":
            os.killpg(runner.pid, signal.SIGINT)  # what the terminal does
        else:
            runner.send_signal(signal.SIGTERM)  # the launcher alone, not its group
        out, _ = runner.communicate(timeout=30)
    finally:
        if runner.poll() is None:
            runner.kill()
    lines = log.read_text().split("\n")
    assert [line for line in lines if "stop" in line] == ["driver stopping", "driver stopped", "bus stopping",
                                                          "bus stopped"], out
    assert runner.returncode == 0, out


def test_a_process_that_fails_stops_the_others_and_the_launcher_fails(tmp_path: Path) -> None:
    """The driver ending with an error (a boot error: a link not up yet) stops the rest and the
    launcher exits non-zero, so systemd starts the service again (`ros2 launch` exits 0 there)."""
    (tmp_path / "failer.py").write_text(  # once the other is ready: its stop is then its own SIGINT handler's
        "import os, sys, time\n"
        "while not (os.path.exists(sys.argv[1]) and 'bus ready' in open(sys.argv[1]).read()):\n"
        "    time.sleep(0.02)\n"
        "open(sys.argv[1], 'a').write('driver failed\\n')\nsys.exit(2)\n")
    launch = write_launch(tmp_path)
    launch.write_text('<launch>\n  <arg name="py" default="python3"/>\n  <arg name="log" default="log.txt"/>\n'
                      '  <executable cmd="$(var py) stopper.py bus $(var log)"/>\n'
                      '  <executable cmd="$(var py) failer.py $(var log)"/>\n</launch>\n')
    log = tmp_path / "log.txt"
    runner = run_launcher(tmp_path, launch, log)
    try:
        out, _ = runner.communicate(timeout=60)
    finally:
        if runner.poll() is None:
            runner.kill()
    assert runner.returncode == 1, out
    assert "exited with 2; stopping the others" in out, out
    assert "bus stopped" in log.read_text(), log.read_text()


ROVER_LAUNCH = BRINGUP / "launch" / "rover_launch.xml"
DRIVER_NODES = {"rovercan_driver", "drive_system", "rovercan_driver_services", "rovercan_driver_stops",
                "rovercan_driver_actions"}


@requires_ros
def test_the_rover_launch_names_each_node_once_and_its_parameters_answer_alike(tmp_path: Path) -> None:
    """A launch name renames every node of a process (ros2 launch passes __node:=): the rover
    launch gives none, so the driver process's four nodes keep their names, each once in the
    graph, and /rovercan_driver/list_parameters answers the same each time."""
    import rclpy
    from rcl_interfaces.srv import ListParameters

    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                      "drives:\n  - {name: left, node_id: 1, counts_per_rev: 4096}\n"
                      "  - {name: right, node_id: 2, counts_per_rev: 4096}\n"
                      "drive_system: {left: [left], right: [right], track_width_m: 0.5, wheel_radius_m: 0.1,"
                      " max_speed_m_s: 1.0}\n")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    assert all("__node" not in " ".join(p.argv) for p in parse_launch(ROVER_LAUNCH, {"config": str(config)}))
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(ROVER_LAUNCH), "sim:=true",
                             f"config:={config}", "--duration", "90"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context, probe, executor = ros_probe("launch_probe")
    try:
        names: list[str] = []
        deadline = time.monotonic() + 60.0  # the processes start on two cores, then DDS discovery
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.2)
            names = [n for n, ns in probe.get_node_names_and_namespaces() if ns == "/"]
            if set(names) >= DRIVER_NODES:
                break
        assert set(names) >= DRIVER_NODES, (names, proc.poll())
        client = probe.create_client(ListParameters, "/rovercan_driver/list_parameters")
        assert client.wait_for_service(timeout_sec=20.0)
        answers = []
        for _ in range(3):
            future = client.call_async(ListParameters.Request())
            executor.spin_until_future_complete(future, timeout_sec=10.0)
            assert future.result() is not None
            answers.append(sorted(future.result().result.names))
        assert answers[0] == answers[1] == answers[2] and "config" in answers[0], answers
        # judged once the driver process answered: it makes all its nodes before it serves any
        # (nodes/assembly.py), and the probe has heard that process, so a twin name is in the graph
        names = [n for n, ns in probe.get_node_names_and_namespaces() if ns == "/"]
        # the launch's own names: another test's client nodes in this worker's DDS domain can linger
        # in the graph a while (three trajectory_client seen beside a loaded CI), and are not its
        made = [n for n in names if n.startswith(("rovercan_", "drive_system", "motor_"))]
        assert len(made) == len(set(made)), f"a node name twice: {sorted(made)} (the graph: {sorted(names)})"
    finally:
        probe.destroy_node()
        rclpy.shutdown(context=context)
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert "Publisher already registered" not in out, out[-3000:]

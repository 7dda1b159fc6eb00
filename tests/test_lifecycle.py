"""rover_lifecycle walked through configure, activate, deactivate, cleanup and shutdown, each
transition checked on the bus by an independent listener and on the simulated drives."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from can_config import GENERIC_EDS
from virtual_can import SimDriveSpec, SimService

from .conftest import HAVE_ROS, requires_ros, wait_for
from .test_ros_interface import check_assembly

pytestmark = requires_ros

if HAVE_ROS:
    import can
    import rclpy
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from nodes.rover_lifecycle import DriveLifecycleNode
    from nodes.runtime import SpinThread, make_executor


class Listener(threading.Thread):
    def __init__(self, sim: SimService) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        self.frames: list[tuple[float, int, bytes]] = []
        self.stop = threading.Event()
        self.start()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def since(self, t: float, cob: int) -> list[bytes]:
        return [d for tt, c, d in list(self.frames) if tt >= t and c == cob]


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[Any, SimService, Listener, Any]]:
    sim = SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "a", 4096), SimDriveSpec(2, GENERIC_EDS, "can0", "b", 4096)],
                     port=0)
    config = tmp_path / "rover.yaml"
    config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}]\n"
                      # a homes slowly (method 17 at 0.5 deg/s toward the index: the simulated drive's is
                      # moved far away by the test that needs it); every other test leaves homing alone
                      "drives: [{name: a, node_id: 1, counts_per_rev: 4096, homing_method: 17, homing_speed_deg_s: 0.5,"
                      " homing_timeout_s: 600}, {name: b, node_id: 2, counts_per_rev: 4096}]\n")
    context = rclpy.Context()
    rclpy.init(context=context)
    hot = make_executor("events", context)
    spin = SpinThread(hot, "test-hot")
    node = DriveLifecycleNode(hot, context=context, parameter_overrides=[Parameter("config", value=str(config))])
    cold = SingleThreadedExecutor(context=context)  # its lifecycle services, as main spins them
    cold.add_node(node)
    transitions = SpinThread(cold, "test-lifecycle")
    listener = Listener(sim)
    yield node, sim, listener, config
    listener.stop.set()
    listener.join(2)
    listener.bus.shutdown()
    node.release()
    transitions.stop(5.0)
    spin.stop(5.0)
    node.destroy_node()
    rclpy.shutdown(context=context)
    sim.close()


def states(sim: SimService) -> list[str]:
    runner = sim.simulators["can0"]
    return runner.call(lambda: [runner.drive(n).state.name for n in (1, 2)])


def controlwords(listener: Listener, t: float, cob: int) -> list[int]:
    return [int.from_bytes(d[:2], "little") for d in listener.since(t, cob)]


def test_each_transition_is_confirmed_on_the_bus(rig: tuple[Any, SimService, Listener, Any]) -> None:
    node, sim, listener, _ = rig
    assert node._state_machine.current_state[1] == "unconfigured"
    time.sleep(0.3)
    assert not listener.since(0.0, 0x77F)  # nothing of the driver on the bus yet

    t = time.monotonic()
    node.trigger_configure()
    assert node._state_machine.current_state[1] == "inactive"
    assert node.driver is not None and all(d.cache.booted for d in node.driver)
    check_assembly(node.assembly, "rovercan_driver", ["a", "b"])  # rover_driver's nodes, executors, groups
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2  # booted, not enabled
    wait_for(lambda: len(listener.since(t, 0x77F)) >= 2, 2.0, "the driver's host heartbeat")
    assert {d[:2] for d in listener.since(t, 0x000)} >= {bytes([0x81, 1]), bytes([0x81, 2])}  # NMT reset: boot

    node.trigger_activate()
    assert node._state_machine.current_state[1] == "active"
    assert states(sim) == ["OPERATION_ENABLED"] * 2

    t = time.monotonic()
    node.trigger_deactivate()
    assert node._state_machine.current_state[1] == "inactive"
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2
    for cob in (0x201, 0x202):  # each drive quick-stopped (controlword 0x0002) before being disabled
        # the listener shares this interpreter with the node, the driver and the simulator, and
        # under load it reads the bus late (a loaded run: nothing of 0x202 yet when it was asked
        # right after the transition, although the drive was disabled): wait for what it will see
        wait_for(lambda cob=cob: 0x0002 in controlwords(listener, t, cob), 2.0,
                 f"controlword 0x0002 on 0x{cob:03X}")

    node.trigger_cleanup()
    assert node._state_machine.current_state[1] == "unconfigured" and node.driver is None
    time.sleep(0.3)
    t = time.monotonic()
    time.sleep(0.5)
    assert not listener.since(t, 0x77F) and not listener.since(t, 0x080)  # no heartbeat, no SYNC: bus released
    assert len(sim.server.clients) == 1  # only the listener is connected

    node.trigger_shutdown()
    assert node._state_machine.current_state[1] == "finalized"


def test_through_the_lifecycle_services_one_joints_enable_answers_while_another_homes(
        rig: tuple[Any, SimService, Listener, Any]) -> None:
    """Configured and activated through the standard lifecycle service (change_state), as a
    lifecycle manager does: joint a homes slowly (until stopped); b's /quick_stop, /enable and the
    rover's /arm answer meanwhile (order, not a clock: each answer arrives while /home has not
    answered and a is still busy homing). The landed lifecycle node ran every service on one
    thread: b's /enable answered after a's /home."""
    node, sim, _, _ = rig
    probe = rclpy.create_node("lifecycle_probe", context=node.context)
    node.hot.add_node(probe)

    def ask(srv_type: Any, name: str, request: Any) -> Any:
        client = probe.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=10.0), f"no service {name}"
        return client.call_async(request)

    def answer(future: Any, what: str) -> Any:
        wait_for(future.done, 30.0, what)
        return future.result()

    try:
        for step in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
            reply = answer(ask(ChangeState, "/rovercan_lifecycle/change_state",
                               ChangeState.Request(transition=Transition(id=step))), f"transition {step}")
            assert reply.success, step
        assert states(sim) == ["OPERATION_ENABLED"] * 2
        runner = sim.simulators["can0"]
        runner.call(lambda: setattr(runner.drive(1).params, "index_position_counts", 10**9))  # far: a homes until stopped
        drive_a = node.driver.drive("a")
        home = ask(Trigger, "a/home", Trigger.Request())
        wait_for(lambda: drive_a.channel.busy == "home", 10.0, "a homing")
        for service in ("b/quick_stop", "b/enable"):
            reply = answer(ask(Trigger, service, Trigger.Request()), service)
            assert reply.success, reply.message
            assert not home.done() and drive_a.channel.busy == "home", service  # answered while a still homes
        assert states(sim)[1] == "OPERATION_ENABLED"
        armed = answer(ask(Trigger, "arm", Trigger.Request()), "/arm")
        assert not home.done() and drive_a.channel.busy == "home"
        assert not armed.success and "busy with home" in armed.message, armed.message  # a named, b enabled
        reply = answer(ask(ChangeState, "/rovercan_lifecycle/change_state",
                           ChangeState.Request(transition=Transition(id=Transition.TRANSITION_DEACTIVATE))), "deactivate")
        assert reply.success
        homed = answer(home, "/home interrupted by the deactivate's stop")
        assert not homed.success, homed.message
        assert states(sim) == ["SWITCH_ON_DISABLED"] * 2
    finally:
        node.hot.remove_node(probe)
        probe.destroy_node()


def test_a_failed_configure_leaves_nothing_behind(rig: tuple[Any, SimService, Listener, Any]) -> None:
    node, sim, listener, config = rig
    config.write_text("buses: [{name: can0, interface: socketcand, channel: can0, kwargs: {host: 127.0.0.1, port: 1},"
                      " connect_timeout_ms: 200}]\ndrives: [{name: a, node_id: 1}]\n")
    node.trigger_configure()
    assert node._state_machine.current_state[1] == "unconfigured" and node.driver is None
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2 and not listener.since(0.0, 0x77F)


def test_autostart_arms_the_drives_and_sigterm_leaves_them_safe(tmp_path: Path) -> None:
    """The demo's auto-start: `autostart:=true` configures and activates at start (every thread
    under SCHED_FIFO where allowed); SIGTERM (what systemd and docker stop send) stops and disables
    every drive before the bus closes."""
    import os
    import signal
    import subprocess
    import sys

    from rovercan.launch import parse_launch

    from .conftest import REPO, realtime_allowed
    from .test_shutdown import thread_policies

    launched = parse_launch(REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml",
                            {"config": "/x.yaml", "lifecycle": "true", "autostart": "true"})
    assert [p.name for p in launched] == ["rover_lifecycle"] and "autostart:=true" in launched[0].argv
    assert "nodes.rover_lifecycle" in launched[0].argv and "__node:=" not in " ".join(launched[0].argv)  # its own name
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "a", 4096)], port=0) as sim:
        config = tmp_path / "rover.yaml"
        config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                          f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}]\n"
                          "drives: [{name: a, node_id: 1, counts_per_rev: 4096}]\n")
        proc = subprocess.Popen([sys.executable, "-m", "nodes.rover_lifecycle", "--ros-args", "-p",
                                 f"config:={config}", "-p", "autostart:=true"], cwd=REPO,
                                env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        runner = sim.simulators["can0"]
        try:
            wait_for(lambda: runner.call(lambda: runner.drive(1).state.name) == "OPERATION_ENABLED", 20.0, "armed")
            if realtime_allowed():  # the driver it made runs its threads under SCHED_FIFO, as rover_driver's
                policies = thread_policies(proc.pid)  # the bus's receive thread included (motor_driver/bus/handle.py)
                assert set(policies) == {os.SCHED_FIFO}, policies
        finally:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=20)
        assert proc.returncode == 0, out[-2000:]
        assert runner.call(lambda: runner.drive(1).state.name) == "SWITCH_ON_DISABLED", out[-2000:]

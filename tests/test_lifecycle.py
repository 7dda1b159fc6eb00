"""rover_lifecycle walked through configure, activate, deactivate, cleanup and shutdown, each
transition checked on the bus by an independent listener and on the simulated drives."""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from can_config import GENERIC_EDS
from virtual_can import SimDriveSpec, SimService

from .conftest import HAVE_ROS, IN_PROCESS_HEARTBEAT_TIMEOUT_MS, IN_PROCESS_HOST_TIMEOUT_MS, requires_ros, wait_for
from .test_ros_interface import check_assembly

pytestmark = requires_ros

if HAVE_ROS:
    import can
    import rclpy
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.lifecycle import TransitionCallbackReturn
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from nodes.process.spinning import SpinThread, make_executor
    from nodes.rover_lifecycle import DriveLifecycleNode


class Listener(threading.Thread):
    """An independent python-can client of the simulator's bus: every frame, in order, with when it came."""

    def __init__(self, sim: SimService | None, *, port: int = 0, channel: str = "can0") -> None:
        super().__init__(daemon=True)
        host, port = (sim.host, sim.port) if sim is not None else ("127.0.0.1", port)
        self.bus = can.Bus(interface="socketcand", channel=channel, host=host, port=port)
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

    def heard_marker(self, sim: SimService, number: int) -> int:
        """Send marker ``number`` from another client of the bus and wait until this listener heard
        it: everything the bus carried before it reached the listener too (the bus keeps the order).
        Returns how many frames the listener had heard up to and with the marker."""
        data = number.to_bytes(4, "little")
        with can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) as bus:
            bus.send(can.Message(arbitration_id=MARKER_COB, data=data, is_extended_id=False))
            wait_for(lambda: any(c == MARKER_COB and d == data for _, c, d in list(self.frames)), 10.0,
                     f"marker {number} at the listener (is it listening?)")
        return next(i for i, (_, c, d) in enumerate(list(self.frames)) if c == MARKER_COB and d == data) + 1

    def between(self, first: int, last: int, cobs: tuple[int, ...]) -> list[int]:
        """The COB-IDs of ``cobs`` heard between two markers (indexes from :meth:`heard_marker`)."""
        return [c for _, c, _ in list(self.frames)[first:last] if c in cobs]


#: A COB-ID no CANopen service of these drives uses: the test's markers.
MARKER_COB = 0x500


#: The drives and the test share one interpreter: the in-process host and heartbeat timeouts (conftest says why).
_TIMEOUTS = f"host_timeout_ms: {IN_PROCESS_HOST_TIMEOUT_MS:g}, heartbeat_timeout_ms: {IN_PROCESS_HEARTBEAT_TIMEOUT_MS:g}"
RIG_DRIVES = ("drives: [{name: a, node_id: 1, counts_per_rev: 4096, homing_method: 17, homing_speed_deg_s: 0.5,"
              f" homing_timeout_s: 600, {_TIMEOUTS}}}, {{name: b, node_id: 2, counts_per_rev: 4096, {_TIMEOUTS}}}]\n")


@contextmanager
def make_rig(tmp_path: Path, *, args: tuple[str, ...] = (), extra: str = "") -> Iterator[tuple[Any, SimService, Listener, Any]]:
    """The lifecycle node on a simulated bus of two drives, spun as ``main`` spins it; ``args``:
    parameters of every node of the process (``-p name:=value``); ``extra``: config appended."""
    sim = SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "a", 4096), SimDriveSpec(2, GENERIC_EDS, "can0", "b", 4096)],
                     port=0)
    config = tmp_path / "rover.yaml"
    config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}]\n"
                      # a homes slowly (method 17 at 0.5 deg/s toward the index: the simulated drive's is
                      # moved far away by the test that needs it); every other test leaves homing alone
                      + RIG_DRIVES + extra)
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", *(a for arg in args for a in ("-p", arg))] if args else None)
    hot = make_executor("events", context)
    spin = SpinThread(hot, "test-hot")
    node = DriveLifecycleNode(hot, context=context, parameter_overrides=[Parameter("config", value=str(config))])
    cold = SingleThreadedExecutor(context=context)  # its lifecycle services, as main spins them
    cold.add_node(node)
    transitions = SpinThread(cold, "test-lifecycle")
    listener = Listener(sim)
    try:
        yield node, sim, listener, config
    finally:
        listener.stop.set()
        listener.join(2)
        listener.bus.shutdown()
        node.release()
        transitions.stop(5.0)
        spin.stop(5.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
        sim.close()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[Any, SimService, Listener, Any]]:
    """Activate arms every drive (``arm:=true``, as ``autostart`` with ``arm`` does)."""
    with make_rig(tmp_path, args=("arm:=true",)) as made:
        yield made


def states(sim: SimService) -> list[str]:
    runner = sim.simulators["can0"]
    return runner.call(lambda: [runner.drive(n).state.name for n in (1, 2)])


def controlwords(listener: Listener, t: float, cob: int) -> list[int]:
    return [int.from_bytes(d[:2], "little") for d in listener.since(t, cob)]


def test_each_transition_is_confirmed_on_the_bus(rig: tuple[Any, SimService, Listener, Any]) -> None:
    node, sim, listener, _ = rig
    assert node._state_machine.current_state[1] == "unconfigured"
    heard = listener.heard_marker(sim, 1)  # the listener heard everything up to now
    assert not listener.between(0, heard, (0x77F, 0x080))  # nothing of the driver on the bus yet

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
    wait_for(lambda: len(sim.server.clients) == 1 and len(sim.server.cyclic) == 0, 10.0,
             "the bus's own record: only the listener connected, no cyclic job (the SYNC's) left")
    # and the listener shows it: between two markers a few of each drive's heartbeats apart (the
    # bus's own clock, each 100 ms and longer than the SYNC and host heartbeat periods), no SYNC and
    # no host heartbeat
    first = listener.heard_marker(sim, 2)
    wait_for(lambda: all(listener.between(first, len(listener.frames), (0x700 + n,)).count(0x700 + n) >= 3
                         for n in (1, 2)), 10.0, "three heartbeats of each drive after the release")
    last = listener.heard_marker(sim, 3)
    assert not listener.between(first, last, (0x77F, 0x080))  # no heartbeat, no SYNC: bus released

    node.trigger_shutdown()
    assert node._state_machine.current_state[1] == "finalized"


def test_a_lost_drive_does_not_keep_the_node_active_and_a_failed_stop_does(
        rig: tuple[Any, SimService, Listener, Any]) -> None:
    """Deactivate with drive b lost (its transmitter dead: a last quick stop sent, which it cannot
    answer, at every deactivate alike): the node goes inactive, drive a safe, and the lost drive is
    not said to be stopped. A reachable drive's stop that fails keeps the node active (motion held),
    as before: deactivating again may confirm it. (A Nav2 manager's PAUSE failed for as long as a
    wheel stayed unplugged, the node active while every reachable drive was disabled.)"""
    from can_config.errors import DriveTimeoutError
    from virtual_can.scenario import apply_action

    node, sim, _, _ = rig
    node.trigger_configure()
    node.trigger_activate()
    assert states(sim) == ["OPERATION_ENABLED"] * 2
    apply_action(sim, {"action": "tx_dead", "node": 2})
    wait_for(lambda: node.driver.drive("b").cache.lost, 10.0, "b lost")
    a = node.driver.drive("a")
    quick_stop = a.quick_stop

    def refused() -> None:
        raise DriveTimeoutError("a: the quick stop was not confirmed (a test's refusal)")

    a.quick_stop = refused
    node.trigger_deactivate()
    assert node._state_machine.current_state[1] == "active"  # a's stop failed: trying again may help
    assert "deactivate did not confirm every stop" in (node.driver.motion_held or "")
    assert states(sim)[0] == "OPERATION_ENABLED"  # held, not stopped: the failed stop left it as it was

    a.quick_stop = quick_stop
    node.trigger_deactivate()
    assert node._state_machine.current_state[1] == "inactive"  # b lost: said, not a failure
    assert states(sim)[0] == "SWITCH_ON_DISABLED"
    said = node._drives_safe(node.stop_drives())  # what the transition's line says of the drives
    assert said.startswith("1 drive(s) quick-stopped") and said.endswith(", 1 lost"), said


def test_a_step_of_the_release_that_raises_stops_none_of_the_others(rig: tuple[Any, SimService, Listener, Any]) -> None:
    """Cleanup with the driver's release of its host watch raising (a bug): the rest of the
    teardown goes on. It stopped at the first failure: the buses stayed connected with their
    SYNC, the executor threads ran and the nodes stayed in the graph while error processing said
    all was released, and every configure after it met its own SYNC as another master's."""
    node, sim, _, _ = rig
    node.trigger_configure()
    assert node._state_machine.current_state[1] == "inactive"

    def broken() -> None:
        raise RuntimeError("a bug in the release of the host watch (the test's)")

    node.driver._release_host_watch = broken
    node.trigger_cleanup()  # ends in ERROR processing, which releases what is left
    assert node._state_machine.current_state[1] == "unconfigured" and node.assembly is None
    assert node.callback_failures.snapshot()[0] >= 1  # said and counted as the bug it is
    wait_for(lambda: len(sim.server.clients) == 1 and len(sim.server.cyclic) == 0, 10.0,
             "the bus released: only the listener connected, no SYNC job")
    wait_for(lambda: node.get_node_names() == ["rovercan_lifecycle"], 10.0, "the driver's nodes out of the graph")
    node.trigger_configure()
    assert node._state_machine.current_state[1] == "inactive"  # no SYNC of its own left behind to refuse it


def test_after_a_stop_signal_motion_is_held_and_no_activate_arms(rig: tuple[Any, SimService, Listener, Any]) -> None:
    """main's stop: motion held at once (``stop_for_exit``), before its wait for a transition under
    way (up to a minute), and an activate a manager asked for meanwhile arms nothing: FAILURE."""
    node, sim, _, _ = rig
    node.trigger_configure()
    node.stop_for_exit()
    assert "shutting down" in node.driver.motion_held
    assert node.trigger_activate() == TransitionCallbackReturn.FAILURE
    assert node._state_machine.current_state[1] == "inactive" and "shutting down" in node.driver.motion_held
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2  # the rig's arm:=true armed nothing


@pytest.mark.parametrize("arg", ["arm:=1", "state_rate_hz:=100000.0", "odom_rate_hz:=20"])
def test_a_parameter_of_the_wrong_type_or_range_fails_configure_naming_it(tmp_path: Path, arg: str) -> None:
    """``-p arm:=1`` (an integer for a bool), a rate out of its range, or the drive system's rate as
    an integer (refused after the driver node was made): configure FAILS, naming the parameter
    and what it takes, the bus released and no node of the driver left in the graph; no ERROR, no
    "bug" counted (rclpy's exception escaped the transition: ERROR processing, counted in
    callback_failures as a bug; a node made before the refusal stayed in the graph)."""
    with make_rig(tmp_path, args=(arg,), extra=DRIVE_SYSTEM) as (node, sim, _, _):
        assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert node._state_machine.current_state[1] == "unconfigured" and node.driver is None
        assert node.callback_failures.snapshot()[0] == 0
        wait_for(lambda: len(sim.server.clients) == 1, 10.0, "the bus released (only the listener connected)")
        wait_for(lambda: node.get_node_names() == ["rovercan_lifecycle"], 10.0, "no node of the driver left")


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
    """The demo's auto-start: `autostart:=true arm:=true` configures, activates and arms at start (every thread
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
                            {"config": "/x.yaml", "lifecycle": "true", "autostart": "true", "arm": "true"})
    assert [p.name for p in launched] == ["rover_lifecycle"] and {"autostart:=true", "arm:=true"} <= set(launched[0].argv)
    assert "nodes.rover_lifecycle" in launched[0].argv and "__node:=" not in " ".join(launched[0].argv)  # its own name
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "a", 4096)], port=0) as sim:
        config = tmp_path / "rover.yaml"
        config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                          f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}]\n"
                          "drives: [{name: a, node_id: 1, counts_per_rev: 4096}]\n")
        proc = subprocess.Popen([sys.executable, "-m", "nodes.rover_lifecycle", "--ros-args", "-p",
                                 f"config:={config}", "-p", "autostart:=true", "-p", "arm:=true"], cwd=REPO,
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


# ---------------------------------------------------------------------------- motion held while not active
INACTIVE = "rovercan_lifecycle is inactive: activate it"
#: The wheels of the drive system: a left, b right.
DRIVE_SYSTEM = "drive_system: {left: [a], right: [b], track_width_m: 0.6, wheel_radius_m: 0.1, cmd_timeout_ms: 500}\n"


def rpdo(cob_id: int) -> bool:
    """An RPDO of a drive: a controlword or a set-point (nothing else goes host -> drive on them)."""
    return cob_id & 0x780 in (0x200, 0x300, 0x400, 0x500) and cob_id & 0x7F != 0


def set_point(cob_id: int) -> bool:
    """An RPDO but the first (the controlword's): a target."""
    return rpdo(cob_id) and cob_id & 0x780 != 0x200


#: The fence's SDO upload request: 0x1000 (device type), which nothing but a boot reads.
FENCE = bytes([0x40, 0x00, 0x10, 0x00])


class Probe:
    """A client node of the graph on an executor of its own, spun on the test's thread while it
    waits (rclpy's clients match an answer to a request recorded after it was sent: an executor
    spinning on another thread can take the answer first and drop it): services, actions,
    publishers, and every /diagnostics status it heard."""

    def __init__(self, context: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.action import ActionClient
        from rovercan_msgs.action import Home, MoveJoint

        self.node = rclpy.create_node("lifecycle_motion_probe", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.statuses: list[tuple[str, str, dict[str, str]]] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)
        self.actions = {"move_joint": ActionClient(self.node, MoveJoint, "move_joint"),
                        "home_joint": ActionClient(self.node, Home, "home_joint")}
        self.pubs: dict[str, Any] = {}

    def _on_diagnostics(self, msg: Any) -> None:
        self.statuses += [(s.name, s.message, {kv.key: kv.value for kv in s.values}) for s in msg.status]

    def wait(self, done: Any, hang_s: float, what: str, said: Any = None) -> None:
        """``wait_for(done)``, the probe's node spun meanwhile."""
        def spun() -> bool:
            self.executor.spin_once(timeout_sec=0.005)
            return bool(done())
        wait_for(spun, hang_s, what, said)

    def close(self) -> None:
        self.executor.shutdown()
        for client in self.actions.values():
            client.destroy()
        self.node.destroy_node()

    def call(self, srv_type: Any, name: str, request: Any, hang_s: float = 30.0) -> Any:
        client = self.node.create_client(srv_type, name)
        try:
            assert client.wait_for_service(timeout_sec=hang_s), f"no service {name}"
            future = client.call_async(request)
            self.wait(future.done, hang_s, f"{name} answered")
            return future.result()
        finally:
            self.node.destroy_client(client)

    def goal(self, action: str, goal: Any) -> Any:
        client = self.actions[action]
        assert client.wait_for_server(timeout_sec=10.0), f"no action server {action}"
        sent = client.send_goal_async(goal)
        self.wait(sent.done, 30.0, f"{action} goal answered")
        handle = sent.result()
        if not handle.accepted:
            return None
        result = handle.get_result_async()
        self.wait(result.done, 30.0, f"{action} result")
        return result.result().result

    def publisher(self, msg_type: Any, topic: str) -> Any:
        if topic not in self.pubs:
            self.pubs[topic] = self.node.create_publisher(msg_type, topic, 10)
        return self.pubs[topic]

    def refused_on_topic(self, msg_type: Any, topic: str, msg: Any, status: str, *said: str) -> str:
        """Publish ``msg`` on ``topic`` until /diagnostics' ``status`` reports a refusal saying
        each of ``said`` (every refusal is counted there, none held back); that report."""
        pub = self.publisher(msg_type, topic)
        since = len(self.statuses)
        found: list[str] = []

        def refused() -> bool:
            pub.publish(msg)
            for name, message, values in self.statuses[since:]:
                text = values.get("last_refusal") or message
                if name == status and all(s in text for s in said):
                    found.append(text)
                    return True
            return False

        self.wait(refused, 20.0, f"a refusal of {topic} on /diagnostics ({status})",
                 lambda: "\n".join(f"{n}: {m}" for n, m, _ in self.statuses[since:][-10:]))
        return found[0]


def motion_entries() -> list[tuple[str, Any]]:
    """Every motion entry of the node: (what, how to try it with a Probe -> what it answered).
    Read from the code: the services that wait (nodes/joints/driver_services.py), the command topics
    (nodes/rover_driver.py, the drive system's /cmd_vel) and the actions (nodes/actions/driver_actions.py)."""
    from geometry_msgs.msg import Twist
    from rovercan_msgs.action import Home, MoveJoint
    from rovercan_msgs.srv import SdoWrite, SetMode
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32

    def trigger(name: str) -> Any:
        return lambda probe: probe.call(Trigger, name, Trigger.Request()).message

    def topic(msg_type: Any, name: str, msg: Any, status: str, said: str) -> Any:
        return lambda probe: probe.refused_on_topic(msg_type, name, msg, status, said)

    def action(name: str, goal: Any) -> Any:
        def run(probe: Probe) -> str:
            result = probe.goal(name, goal)
            return "goal rejected without a word" if result is None else result.message
        return run

    return [
        ("/arm", trigger("arm")),
        ("a/enable", trigger("a/enable")),
        ("a/recover", trigger("a/recover")),
        ("a/home", trigger("a/home")),
        ("a/set_mode (the mode it is in)", lambda probe: probe.call(
            SetMode, "a/set_mode", SetMode.Request(mode="profile_position")).message),
        ("a/set_mode", lambda probe: probe.call(SetMode, "a/set_mode", SetMode.Request(mode="profile_velocity")).message),
        ("a/sdo_write", lambda probe: probe.call(
            SdoWrite, "a/sdo_write", SdoWrite.Request(index=0x6065, subindex=0, value=1000)).message),
        ("a/degree_cmd", topic(Float32, "a/degree_cmd", Float32(data=5.0), "rovercan: a", "degree command 5.0")),
        ("a/velocity_cmd", topic(Float32, "a/velocity_cmd", Float32(data=3.0), "rovercan: a", "velocity command 3.0")),
        ("/motor_degree_cmd", topic(Float32, "/motor_degree_cmd", Float32(data=7.0), "rovercan: a", "degree command 7.0")),
        ("/joint_commands", topic(JointState, "/joint_commands", JointState(name=["b"], velocity=[1.0]), "rovercan: b",
                                  "joint velocity")),
        ("/cmd_vel", topic(Twist, "/cmd_vel", Twist(), "rovercan: command input", "/cmd_vel not applied")),
        ("move_joint", action("move_joint", MoveJoint.Goal(joint="a", target_deg=10.0, speed_deg_s=30.0))),
        ("move_joint (no speed)", action("move_joint", MoveJoint.Goal(joint="b", target_deg=10.0))),
        ("home_joint", action("home_joint", Home.Goal(joint="a"))),
    ]


def sim_positions(sim: SimService) -> list[int]:
    runner = sim.simulators["can0"]
    return runner.call(lambda: [runner.drive(n).position_counts for n in (1, 2)])


def fence(probe: Probe, listener: Listener, since: int) -> int:
    """Each drive's statusword read by SDO through the driver (checked: not Operation Enabled),
    then its device type, which nothing but a boot reads: that request is the newest frame the
    driver sent (one connection, frames in order), so everything it sent before is on the
    listener's list before it. The index just past the fence."""
    from rovercan_msgs.srv import SdoRead

    for joint, node_id in (("a", 1), ("b", 2)):
        read = probe.call(SdoRead, f"{joint}/sdo_read", SdoRead.Request(index=0x6041, subindex=0))
        assert read.success and read.value & 0x6F != 0x27, (joint, read.message)  # not Operation Enabled
        assert probe.call(SdoRead, f"{joint}/sdo_read", SdoRead.Request(index=0x1000, subindex=0)).success
        wait_for(lambda node_id=node_id: any(c == 0x600 + node_id and d[:4] == FENCE
                                             for _, c, d in listener.frames[since:]), 10.0, f"the fence of {joint}")
    frames = list(listener.frames)  # the listener appends meanwhile
    return 1 + max(i for i, (_, c, d) in enumerate(frames) if i >= since and c in (0x601, 0x602) and d[:4] == FENCE)


def moving_frames(frames: list[tuple[int, bytes]]) -> list[str]:
    """Frames that enable or move: any RPDO (a controlword or a set-point), an SDO write."""
    return [f"0x{c:03X} {d.hex()}" for c, d in frames
            if rpdo(c) or (0x600 < c < 0x680 and d[0] >> 5 == 1)]


def check_every_entry_refused(node: Any, sim: SimService, listener: Listener, probe: Probe) -> None:
    """Every motion entry refused, saying the lifecycle state and what helps; on the bus, no
    frame that enables or moves; no drive enabled, none moved."""
    since, positions = fence(probe, listener, len(listener.frames)), sim_positions(sim)  # the stops before: read
    wrong = []
    for what, attempt in motion_entries():
        try:
            said = attempt(probe)
        except AssertionError as err:  # a topic's command not refused at all
            said = str(err)
        if INACTIVE not in said:
            wrong.append(f"{what}: {said}")
    assert not wrong, "\n".join(wrong)
    moved = moving_frames([(c, d) for _, c, d in listener.frames[since:fence(probe, listener, since)]])
    assert not moved, moved
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2
    assert sim_positions(sim) == positions


def check_active_drives(node: Any, sim: SimService, listener: Listener, probe: Probe) -> None:
    """Activated: nothing enabled by that alone; /arm enables both, /cmd_vel turns the wheels
    (set-points on the bus)."""
    from geometry_msgs.msg import Twist

    node.trigger_activate()
    assert node._state_machine.current_state[1] == "active"
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2  # activate enables nothing by itself (arm is false)
    armed = probe.call(Trigger, "arm", Trigger.Request())
    assert armed.success, armed.message
    since, positions = len(listener.frames), sim_positions(sim)
    cmd_vel = probe.publisher(Twist, "/cmd_vel")
    forward = Twist()
    forward.linear.x = 0.2

    def turning() -> bool:
        cmd_vel.publish(forward)
        return all(abs(p - q) > 100 for p, q in zip(sim_positions(sim), positions, strict=True))

    probe.wait(turning, 30.0, "both wheels turning on /cmd_vel",
             lambda: "\n".join(f"{n}: {m}" for n, m, _ in probe.statuses[-8:]))
    assert states(sim) == ["OPERATION_ENABLED"] * 2
    assert any(set_point(c) for _, c, _ in listener.frames[since:])  # set-points on the bus


@pytest.mark.parametrize("state", ["unconfigured", "configured", "deactivated"])
def test_while_not_active_every_motion_entry_is_refused_and_nothing_moves(tmp_path: Path, state: str) -> None:
    """Unconfigured: no driver, no motion entry served, nothing on the bus. Configured (inactive)
    and deactivated after driving: every motion entry (motion_entries) answers or reports
    "rovercan_lifecycle is inactive: activate it"; an independent listener on the bus sees no
    RPDO (no controlword, no set-point) and no SDO write from the driver, the simulated drives stay
    Switch On Disabled where they were. Then activate, /arm and /cmd_vel drive the wheels."""
    args = ("diagnostics_rate_hz:=10.0", "default_joint:=a")
    with make_rig(tmp_path, args=args, extra=DRIVE_SYSTEM) as (node, sim, listener, _):
        probe = Probe(node.context)
        try:
            if state == "unconfigured":
                check_nothing_served(node, sim, probe)
                node.trigger_configure()
            else:
                node.trigger_configure()
                assert node._state_machine.current_state[1] == "inactive"
                if state == "deactivated":
                    check_active_drives(node, sim, listener, probe)
                    node.trigger_deactivate()  # while /cmd_vel is fresh: the drive system was driving
                    assert node._state_machine.current_state[1] == "inactive"
                check_every_entry_refused(node, sim, listener, probe)
            check_active_drives(node, sim, listener, probe)
        finally:
            probe.close()


def check_nothing_served(node: Any, sim: SimService, probe: Probe) -> None:
    """Unconfigured: no motion entry exists (no driver: nothing could be sent), the bus is not
    even connected; the node's own lifecycle services are (the graph is up to date)."""
    assert node._state_machine.current_state[1] == "unconfigured" and node.driver is None
    wait_for(lambda: "/rovercan_lifecycle/change_state" in dict(probe.node.get_service_names_and_types()), 10.0,
             "the lifecycle services in the graph")
    # the assembly's nodes (rovercan_*, drive_system, motor_*): another test module's client node
    # that left this worker's DDS domain can linger in the graph a while, and is not this node's
    made = [n for n in probe.node.get_node_names() if n.startswith(("rovercan_", "drive_system", "motor_"))
            and n != "rovercan_lifecycle"]
    assert not made, made  # no node to serve /arm, a joint's services, the actions
    topics = [t for t in ("/a/degree_cmd", "/a/velocity_cmd", "/motor_degree_cmd", "/joint_commands", "/cmd_vel")
              if probe.node.count_subscribers(t)]
    assert not topics, topics
    assert len(sim.server.clients) == 1  # only the listener: the driver does not exist
    assert states(sim) == ["SWITCH_ON_DISABLED"] * 2


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_launched_rover_with_lifecycle_moves_nothing_while_inactive(tmp_path: Path) -> None:
    """The shipped six-wheel rover as a user starts it (`rovercan sim`, then `rovercan launch
    rover_launch.xml lifecycle:=true`), driven through the standard lifecycle service: configured
    (inactive) and deactivated after driving, /arm, a wheel's enable and /cmd_vel are refused
    with the lifecycle state, and independent listeners on both buses see no RPDO and no SDO write
    from the driver, no drive Operation Enabled; active, /arm and /cmd_vel drive the wheels."""
    import subprocess
    import sys

    from geometry_msgs.msg import Twist

    from .conftest import REPO
    from .test_odom_launched import HANG_S, ROVER_LAUNCH, WHEELS, shipped_rover, start_simulator, stop
    from .test_sim_cli import free_port

    port = free_port()
    config = shipped_rover(tmp_path, port)
    sim = start_simulator(config)
    log = (tmp_path / "launch.log").open("w")
    launch = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(ROVER_LAUNCH), f"config:={config}",
                               "lifecycle:=true", "--duration", "600"], cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    listeners = [Listener(None, port=port, channel=bus) for bus in ("can0", "can1")]
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = Probe(context)
    fences = {"can0": "wheels/wheel_front_left", "can1": "wheels/wheel_front_right"}  # node 1 of each bus
    forward = Twist()
    forward.linear.x = 0.2

    def change(transition: int) -> None:
        reply = probe.call(ChangeState, "/rovercan_lifecycle/change_state",
                           ChangeState.Request(transition=Transition(id=transition)), HANG_S)  # six drives' boot
        assert reply.success, (transition, (tmp_path / "launch.log").read_text()[-3000:])

    def bus_fence(since: list[int]) -> list[list[tuple[int, bytes]]]:
        """What each bus carried from ``since`` up to a read of node 1's device type through the
        driver (the newest frame it sent there); each wheel checked not Operation Enabled."""
        from rovercan_msgs.srv import SdoRead

        for wheel in WHEELS:
            read = probe.call(SdoRead, f"wheels/{wheel}/sdo_read", SdoRead.Request(index=0x6041, subindex=0))
            assert read.success and read.value & 0x6F != 0x27, (wheel, read.message)
        seen = []
        for listener, (bus, prefix), start in zip(listeners, fences.items(), since, strict=True):
            assert probe.call(SdoRead, f"{prefix}/sdo_read", SdoRead.Request(index=0x1000, subindex=0)).success
            wait_for(lambda listener=listener, start=start: any(c == 0x601 and d[:4] == FENCE
                                                                for _, c, d in listener.frames[start:]), 30.0,
                     f"the fence on {bus}")
            seen.append([(c, d) for _, c, d in list(listener.frames)[start:]])
        return seen

    def check_refused() -> None:
        since = [len(f) for f in (listener.frames for listener in listeners)]
        synced = bus_fence(since)  # what the driver sent before (its stops) read, then counted from here
        since = [start + len(frames) for start, frames in zip(since, synced, strict=True)]
        for service in ("arm", "wheels/wheel_front_left/enable"):
            said = probe.call(Trigger, service, Trigger.Request()).message
            assert INACTIVE in said, (service, said)
        said = probe.refused_on_topic(Twist, "/cmd_vel", forward, "rovercan: command input", "/cmd_vel not applied")
        assert INACTIVE in said, said
        moved = [moving for frames in bus_fence(since) for moving in moving_frames(frames)]
        assert not moved, moved

    def check_drives() -> None:
        change(Transition.TRANSITION_ACTIVATE)
        armed = probe.call(Trigger, "arm", Trigger.Request())
        assert armed.success, armed.message
        since = [len(listener.frames) for listener in listeners]
        cmd_vel = probe.publisher(Twist, "/cmd_vel")

        def set_points() -> bool:
            cmd_vel.publish(forward)
            return all(any(set_point(c) for _, c, _ in list(listener.frames)[start:])
                       for listener, start in zip(listeners, since, strict=True))

        probe.wait(set_points, 60.0, "set-points on both buses")

    try:
        change(Transition.TRANSITION_CONFIGURE)
        check_refused()
        check_drives()
        change(Transition.TRANSITION_DEACTIVATE)
        check_refused()
    finally:
        probe.close()
        rclpy.shutdown(context=context)
        for listener in listeners:
            listener.stop.set()
            listener.join(2)
            listener.bus.shutdown()
        stop(launch)
        stop(sim)
        log.close()


# ---------------------------------------------------------------------------- the host gone while driving
#: The wheels of the drive system, /cmd_vel held for a minute: they turn until the signal, not
#: stopped before it by the drive system's own command timeout.
DRIVE_SYSTEM_HELD = "drive_system: {left: [a], right: [b], track_width_m: 0.6, wheel_radius_m: 0.1, cmd_timeout_ms: 60000}\n"


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "hung"])
def test_the_active_node_killed_while_driving_leaves_each_drive_to_stop_itself(tmp_path: Path, sig: int) -> None:
    """The managed node in a process of its own (as the launch runs it) on two simulated wheels,
    configured and activated through its lifecycle service (``arm:=true``: activate enables), the
    wheels turning on /cmd_vel; then SIGKILL, or SIGSTOP (frozen, not dead): no handler of ours
    runs. Each drive's host-heartbeat consumer stops it: an independent listener sees its EMCY
    0x8130 and nothing of the host after it, the test's own SDO client reads it disabled and still."""
    from geometry_msgs.msg import Twist

    from .test_host_loss import HANG_S, host_process, signal_the_host_and_see_the_drives_stop, watching, write_config

    drives = [("a", 1, "can0", GENERIC_EDS), ("b", 2, "can0", GENERIC_EDS)]
    with SimService([SimDriveSpec(node, eds, ch, name, 4096) for name, node, ch, eds in drives], port=0) as sim:
        # consumer times as in the in-process rigs: a node starved 150 ms beside the suite would have
        # the drives stop themselves before the signal; the signal outlasts any consumer time
        config = write_config(tmp_path / "rover.yaml", sim.port, drives, host_timeout_ms=IN_PROCESS_HOST_TIMEOUT_MS,
                              heartbeat_timeout_ms=IN_PROCESS_HEARTBEAT_TIMEOUT_MS)
        config.write_text(config.read_text() + DRIVE_SYSTEM_HELD)
        runner = sim.simulators["can0"]
        context = rclpy.Context()
        rclpy.init(context=context)
        probe = Probe(context)
        try:
            with watching(sim, ["can0"]) as watches, host_process(
                    [sys.executable, "-m", "nodes.rover_lifecycle", "--ros-args", "-p", f"config:={config}",
                     "-p", "arm:=true"], tmp_path / "lifecycle.log") as proc:
                for step in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
                    reply = probe.call(ChangeState, "/rovercan_lifecycle/change_state",
                                       ChangeState.Request(transition=Transition(id=step)), HANG_S)
                    assert reply.success, (step, (tmp_path / "lifecycle.log").read_text()[-3000:])
                forward = Twist()
                forward.linear.x = 0.2
                cmd_vel = probe.publisher(Twist, "/cmd_vel")

                def turning() -> bool:
                    cmd_vel.publish(forward)
                    wheels = runner.call(lambda: [(runner.drive(n).state.name, runner.drive(n).omega) for n in (1, 2)])
                    return all(state == "OPERATION_ENABLED" and omega != 0.0 for state, omega in wheels)

                probe.wait(turning, HANG_S, "both wheels enabled and turning on /cmd_vel")
                signal_the_host_and_see_the_drives_stop(proc, sim, watches, drives, sig)
        finally:
            probe.close()
            rclpy.shutdown(context=context)


# ---------------------------------------------------------------------------- what a lifecycle manager meets
def test_a_transition_the_state_does_not_have_is_answered_false_as_rclcpp_answers_it(tmp_path: Path) -> None:
    """rclpy's managed node raises for a change_state whose transition id its state does not have,
    and sends no answer; Nav2's lifecycle_manager asks by id and waits without a bound (its RESET
    after PAUSE asks for deactivate twice). rclcpp's managed node answers success=false: so does
    this one, logs why, counts no failure, and stays where it was. The sequence is Nav2's:
    STARTUP (configure, activate), PAUSE (deactivate), RESET (deactivate, cleanup)."""
    with make_rig(tmp_path, args=("arm:=true",)) as (node, sim, _, _), _probe(node.context) as probe:
        def ask(transition_id: int) -> bool:
            request = ChangeState.Request(transition=Transition(id=transition_id))
            return bool(probe.call(ChangeState, "/rovercan_lifecycle/change_state", request).success)

        for refused in (Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_DEACTIVATE,
                        Transition.TRANSITION_CLEANUP, 99):
            assert not ask(refused), refused
            assert node.state_label == "unconfigured"
        assert [ask(t) for t in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE)] == [True, True]
        assert states(sim) == ["OPERATION_ENABLED"] * 2
        assert ask(Transition.TRANSITION_DEACTIVATE) and node.state_label == "inactive"
        assert not ask(Transition.TRANSITION_DEACTIVATE) and node.state_label == "inactive"  # RESET's first step
        assert ask(Transition.TRANSITION_CLEANUP) and node.state_label == "unconfigured"
        assert node.callback_failures.snapshot()[0] == 0  # a refusal, not a failure
        assert states(sim) == ["SWITCH_ON_DISABLED"] * 2


@contextmanager
def _probe(context: Any) -> Iterator[Probe]:
    probe = Probe(context)
    try:
        yield probe
    finally:
        probe.close()


def test_an_unexpected_exception_in_a_transition_is_logged_counted_and_ends_safe(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """rclpy turns a transition callback's exception into ERROR and logs nothing; here it is logged
    with its trace and counted, and error processing closes the driver, its safe stop first."""
    import logging

    caplog.set_level(logging.INFO)
    with make_rig(tmp_path, args=("arm:=true",)) as (node, sim, _, _):
        node.trigger_configure()
        arm = node.assembly.arm

        def arm_then_fail(joints: Any = None) -> list[str]:
            arm(joints)  # every drive enabled, then a bug
            raise RuntimeError("a bug after the drives were armed")

        node.assembly.arm = arm_then_fail
        node.trigger_activate()
        assert node.state_label == "unconfigured" and node.driver is None  # ERROR, then on_error
        assert states(sim) == ["SWITCH_ON_DISABLED"] * 2
        count, last, _ = node.callback_failures.snapshot()
        assert count == 1 and "a bug after the drives were armed" in last
        assert "RuntimeError: a bug after the drives were armed" in caplog.text  # its trace
        assert "transition on_activate of rovercan_lifecycle failed unexpectedly" in caplog.text


def test_a_stop_during_the_auto_starts_configure_activates_nothing(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """``autostart`` with ``arm:=true``: a stop asked while configure boots the drives (the hook sets
    the stop event there, as SIGTERM's handler does) ends the auto-start after configure: inactive,
    nothing enabled. The same call without a stop then activates and arms (the path the stop cut)."""
    from nodes.assembly import Assembly

    stop = threading.Event()
    boot = Assembly.start

    def stopped_while_booting(self: Any, *args: Any, **kwargs: Any) -> Any:
        stop.set()
        return boot(self, *args, **kwargs)

    with make_rig(tmp_path, args=("arm:=true",)) as (node, sim, _, _):
        monkeypatch.setattr(Assembly, "start", stopped_while_booting)
        node.autostart(stop)
        assert node.state_label == "inactive" and node.driver is not None
        assert "OPERATION_ENABLED" not in states(sim)
        node.autostart(threading.Event())
        assert node.state_label == "active" and states(sim) == ["OPERATION_ENABLED"] * 2


# ---------------------------------------------------------------------------- the bond with Nav2's manager
class ManagerBond:
    """The manager's side of a bond as Nav2's lifecycle_manager makes it after an activate
    (bondcpp: Status on ``bond`` under the managed node's name, its own instance id; formed once the
    other side is heard active), on the probe's node, the real message type."""

    def __init__(self, probe: Probe, node_name: str) -> None:
        import uuid

        from bond.msg import Status

        self.probe, self.id, self.instance_id = probe, node_name, str(uuid.uuid4())
        self.heard: list[Any] = []  # the other side's Statuses, in order
        self.pub = probe.node.create_publisher(Status, "bond", 5)
        self.sub = probe.node.create_subscription(Status, "bond", self._on_status, 100)
        self.status = Status

    def _on_status(self, msg: Any) -> None:
        if msg.id == self.id and msg.instance_id != self.instance_id:
            self.heard.append(msg)

    def say(self, active: bool) -> None:
        msg = self.status(id=self.id, instance_id=self.instance_id, active=active, heartbeat_timeout=4.0,
                          heartbeat_period=0.1)
        self.pub.publish(msg)

    def beating(self, done: Any) -> Any:
        """``done``, looked at after each of this side's heartbeats (they go on while it waits)."""
        def beat() -> bool:
            self.say(True)
            return bool(done())
        return beat

    def close(self) -> None:
        """Gone, as Nav2's manager erases a node's bond after deactivating it."""
        self.probe.node.destroy_publisher(self.pub)
        self.probe.node.destroy_subscription(self.sub)


def test_the_active_node_keeps_a_bond_with_a_nav2_lifecycle_manager(tmp_path: Path) -> None:
    """Nav2's lifecycle_manager (bond_timeout > 0, its default) makes its side of a bond with each
    node after activating it, and fails its STARTUP without the other. rover_lifecycle makes it at
    activate as Nav2's managed nodes do: heartbeats under its name, active, again and again (the
    manager's 4 s timeout watches them); at deactivate one inactive Status breaks it and its
    entities go; a manager that breaks it first is answered inactive and the bond ends."""
    with make_rig(tmp_path) as (node, sim, _, _), _probe(node.context) as probe:
        def change(transition_id: int) -> None:
            request = ChangeState.Request(transition=Transition(id=transition_id))
            assert probe.call(ChangeState, "/rovercan_lifecycle/change_state", request).success, transition_id

        change(Transition.TRANSITION_CONFIGURE)
        assert node.count_publishers("/bond") == 0 and node.bond is None  # no bond before activate
        change(Transition.TRANSITION_ACTIVATE)
        manager = ManagerBond(probe, "rovercan_lifecycle")  # after activate returned, as Nav2's
        probe.wait(lambda: sum(m.active for m in manager.heard) >= 10, 60.0,
                   "ten heartbeats, the manager silent (the node's timer beats on)")
        first = manager.heard[0]
        assert (first.heartbeat_period, first.heartbeat_timeout) == (pytest.approx(0.1), pytest.approx(4.0))
        sides = {m.instance_id for m in manager.heard}
        assert len(sides) == 1 and sides != {manager.instance_id}
        bond = node.bond
        assert bond is not None
        probe.wait(manager.beating(lambda: bond.sister == manager.instance_id), 30.0, "the manager's side heard")
        assert bond.state.name == "ALIVE"
        count = len(manager.heard)
        change(Transition.TRANSITION_DEACTIVATE)  # Nav2's PAUSE
        probe.wait(lambda: any(not m.active for m in manager.heard[count:]), 30.0, "the bond broken by the node")
        assert node.bond is None and node.count_publishers("/bond") == 1  # the manager's
        manager.close()
        # activate again (RESUME): a new bond with a new manager side; the manager breaks this one first
        change(Transition.TRANSITION_ACTIVATE)
        again = ManagerBond(probe, "rovercan_lifecycle")
        bond = node.bond
        assert bond is not None and bond.instance_id not in sides
        probe.wait(again.beating(lambda: bond.sister == again.instance_id), 30.0, "the new manager side heard")
        count = len(again.heard)
        again.say(False)
        probe.wait(lambda: any(not m.active for m in again.heard[count:]), 30.0, "the manager's break answered")
        assert bond.state.name == "DEAD"
        assert states(sim) == ["SWITCH_ON_DISABLED"] * 2  # no arm: the bond moves nothing
        again.close()


def test_a_hung_driver_executor_withholds_the_bond_s_heartbeats(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bond beats from the lifecycle node's own thread, which serves only the transitions; the
    work (commands, /odom, the states) is the hot executor's. With that executor hung (a tick that
    never returns) the heartbeats stop, as a Nav2 node's bond stops with its executor, so a manager
    resets the nodes; they resume once it runs again. The manager's own Statuses, heard by the same
    listener meanwhile, show it listened."""
    from nodes import rover_lifecycle

    monkeypatch.setattr(rover_lifecycle, "HOT_SILENT_MIN_S", 0.2)
    monkeypatch.setattr(rover_lifecycle, "HOT_SILENT_PERIODS", 2)
    with make_rig(tmp_path) as (node, _, _, _), _probe(node.context) as probe:
        node.trigger_configure()
        node.trigger_activate()
        bond = node.bond
        assert bond is not None and node.assembly is not None and node.assembly.node is not None
        manager = ManagerBond(probe, "rovercan_lifecycle")
        own: list[Any] = []
        probe.node.create_subscription(type(manager.status()), "bond",
                                       lambda m: own.append(m) if m.instance_id == manager.instance_id else None, 100)
        try:
            probe.wait(manager.beating(lambda: bond.state.name == "ALIVE"), 60.0, "the bond formed")
            release, held = threading.Event(), threading.Event()

            def hang() -> None:
                held.set()
                release.wait(60.0)

            beats: list[str] = []  # each of the bond timer's runs (it asks alive() once a beat)
            alive = bond._alive
            assert alive is not None

            def counted() -> str:
                beats.append(alive())
                return beats[-1]

            bond._alive = counted
            node.assembly.node._tick_hooks.append(hang)
            try:
                probe.wait(lambda: held.is_set() and bool(bond.withheld), 60.0, "the heartbeats withheld")
                assert "no state tick" in bond.withheld, bond.withheld
                heard, ran, said = len(manager.heard), len(beats), bond.withheld
                probe.wait(lambda: len(beats) >= ran + 5, 60.0, "five beats of the bond's timer, hung")
                # said once as they stopped (an ERROR a beat, each with its new age, flooded a starved node)
                assert bond.withheld == said and beats[-1] != said, (said, beats[-1])
                mine = len(own)  # the listener hears what the manager says after those beats: it listened
                probe.wait(manager.beating(lambda: len(own) >= mine + 3), 60.0, "the manager's own heard")
                assert len(manager.heard) <= heard + 1, manager.heard[heard:]  # one may have been on its way
            finally:
                node.assembly.node._tick_hooks.remove(hang)
                release.set()
            heard = len(manager.heard)
            probe.wait(manager.beating(lambda: sum(m.active for m in manager.heard[heard:]) >= 3), 60.0,
                       "heartbeats again")
            assert bond.withheld == "" and bond.state.name == "ALIVE"
        finally:
            manager.close()


@pytest.mark.parametrize(("rate_hz", "silent_s", "hung"), [(50.0, 0.99, False), (50.0, 1.01, True), (10.0, 1.99, False),
                                                      (10.0, 2.01, True), (1.0, 3.01, True), (1.0, 2.99, False)])
def test_the_hot_executor_counts_as_hung_within_a_manager_s_bond_timeout(rate_hz: float, silent_s: float,
                                                                        hung: bool) -> None:
    """25 state periods without a tick, 1 s at least: a slow state timer (1 Hz: 25 s) is capped at 2 s
    or three periods (3 s at 1 Hz), within Nav2's default 4 s bond_timeout, so a hang is still the
    bond's to report, and a tick two periods late on a busy machine is not one."""
    from nodes.rover_lifecycle import hot_silence

    said = hot_silence(silent_s, 1.0 / rate_hz)
    assert bool(said) is hung, said
    assert not said or said.startswith(f"the driver's executor has run no state tick for {silent_s:.1f} s"), said


def test_a_bond_no_manager_forms_ends_after_the_connect_timeout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No manager speaks bond (activated by hand, or a manager with bond_timeout 0): the bond ends
    after bond's connect timeout (here cut to a few heartbeats) and beats no more, as bondcpp's."""
    from nodes.process import bond as bond_module

    monkeypatch.setattr(bond_module, "CONNECT_TIMEOUT_S", 0.3)
    with make_rig(tmp_path) as (node, _, _, _), _probe(node.context) as probe:
        node.trigger_configure()
        node.trigger_activate()
        bond = node.bond
        assert bond is not None
        probe.wait(lambda: bond.state.name == "DEAD", 60.0, "the bond ended unformed")
        assert bond._timer.is_canceled() and node.state_label == "active"  # the node's activity is not the bond's


def test_no_bond_when_its_heartbeat_period_is_zero(tmp_path: Path) -> None:
    """``bond_heartbeat_period:=0`` (nav2_util's meaning): activate makes no bond."""
    with make_rig(tmp_path, args=("bond_heartbeat_period:=0.0",)) as (node, _, _, _):
        node.trigger_configure()
        node.trigger_activate()
        assert node.state_label == "active" and node.bond is None
        assert node.count_publishers("/bond") == 0


def test_a_bond_heartbeat_that_raises_is_counted_in_diagnostics_and_the_bond_beats_on(tmp_path: Path) -> None:
    """A bug in the bond's timer (one heartbeat raises) is logged, counted in the process's one
    count and said on /diagnostics by the driver node ("rovercan: driver", ``callback_failures``);
    the next heartbeats go out and the bond stays formed: neither the timer nor the executor is lost."""
    with make_rig(tmp_path, args=("diagnostics_rate_hz:=10.0",)) as (node, _, _, _), _probe(node.context) as probe:
        node.trigger_configure()
        node.trigger_activate()
        bond = node.bond
        assert bond is not None and node.assembly is not None and node.assembly.node is not None
        assert node.assembly.node.callback_failures is node.callback_failures  # one count
        manager = ManagerBond(probe, "rovercan_lifecycle")
        try:
            # the manager answers each wait's turn: the bond forms (no connect timeout runs)
            probe.wait(manager.beating(lambda: bond.state.name == "ALIVE"), 60.0, "the bond formed")
            publish = bond._publish
            raised: list[bool] = []

            def publish_failing_once(active: bool) -> None:
                if not raised:
                    raised.append(True)
                    raise RuntimeError("a bug in the bond's heartbeat")
                publish(active)

            bond._publish = publish_failing_once  # type: ignore[method-assign]
            probe.wait(manager.beating(lambda: bool(raised)), 60.0, "the faulty heartbeat ran")
            heard = len(manager.heard)
            probe.wait(manager.beating(lambda: sum(m.active for m in manager.heard[heard:]) >= 3), 60.0,
                       "heartbeats after the fault")

            def said() -> bool:
                return any(name == "rovercan: driver" and values.get("callback_failures") == "1"
                           and "BondHeartbeat._beat" in values.get("last_callback_failure", "")
                           and "a bug in the bond's heartbeat" in values["last_callback_failure"]
                           for name, _, values in probe.statuses)
            probe.wait(manager.beating(said), 60.0, "the bond's failure on /diagnostics", lambda: probe.statuses[-3:])
            count, last, _ = node.callback_failures.snapshot()
            assert count == 1 and "BondHeartbeat._beat" in last
            assert node.state_label == "active" and bond.state.name == "ALIVE"
        finally:
            manager.close()


def test_a_transition_that_raised_is_said_on_diagnostics_after_the_next_configure(tmp_path: Path) -> None:
    """A transition's unexpected exception ends in ERROR, whose processing closes the driver node
    with the driver; the driver node of the next configure says it on /diagnostics all the same."""
    with make_rig(tmp_path, args=("diagnostics_rate_hz:=10.0",)) as (node, _, _, _), _probe(node.context) as probe:
        node.trigger_configure()
        assert node.assembly is not None

        def arm_fails(joints: Any = None) -> list[str]:
            raise RuntimeError("a bug in activate")

        node.assembly.arm = arm_fails  # type: ignore[method-assign]
        node.trigger_activate()
        assert node.state_label == "unconfigured" and node.driver is None
        node.trigger_configure()

        def said() -> bool:
            return any(name == "rovercan: driver" and values.get("callback_failures") == "1"
                       and "transition on_activate" in values.get("last_callback_failure", "")
                       for name, _, values in probe.statuses)
        probe.wait(said, 60.0, "the transition's failure on /diagnostics", lambda: probe.statuses[-3:])

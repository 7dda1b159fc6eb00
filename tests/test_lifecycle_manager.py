"""rover_lifecycle as a lifecycle manager sees it (issue 70): a manager node with the standard
lifecycle_msgs ChangeState and GetState clients (what Nav2's lifecycle_manager calls) walks the
managed node through configure, activate, deactivate, activate, deactivate, cleanup and shutdown
on the shipped six-wheel rover (config/rover.yaml on the simulator), without ``arm``.

- While inactive the drive system's /diagnostics is level OK, "motion held: " and the hold's reason
  (the node inactive), even with /cmd_vel coming (refused: the node is inactive).
- Once active, a /cmd_vel refusal and the drive system's /diagnostics name what is missing now:
  not armed, and /arm or arm:=true; never the inactive node.
- Every transition and the shutdown is logged at INFO on /rosout, saying what was done to the drives.

Counts and states decide; no wall-clock bound."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from can_config import load_config
from virtual_can import SimService

from .conftest import REPO, wait_for

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import Twist  # noqa: E402
from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rcl_interfaces.msg import Log  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS  # noqa: E402
from nodes.process.spinning import SpinThread, make_executor  # noqa: E402
from nodes.rover_lifecycle import DriveLifecycleNode  # noqa: E402

NODE = "rovercan_lifecycle"
HANG_S = 60.0  # a hang only
OK = int.from_bytes(DiagnosticStatus.OK, "little") if isinstance(DiagnosticStatus.OK, bytes) else int(DiagnosticStatus.OK)


def shipped_rover(tmp_path: Path, port: int) -> Path:
    """config/rover.yaml on ``port``, with the in-process consumer times of tests/test_odom_truth.py."""
    data = yaml.safe_load((REPO / "config" / "rover.yaml").read_text())
    for bus in data["buses"]:
        bus["kwargs"]["port"] = port
    for drive in data["drives"]:
        drive.update(host_timeout_ms=2000, heartbeat_timeout_ms=2500)
    path = tmp_path / "rover.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class Manager:
    """The managed node spun as ``rover_lifecycle`` spins it, and a manager node beside it: the
    lifecycle services' clients, /cmd_vel, and listeners on /diagnostics and /rosout."""

    def __init__(self, tmp_path: Path) -> None:
        shipped = load_config(REPO / "config" / "rover.yaml")
        self.sim = SimService.from_config(dataclasses.replace(shipped), port=0)
        config = shipped_rover(tmp_path, self.sim.port)
        self.context = rclpy.Context()
        domain = None if os.environ.get("ROS_DOMAIN_ID") else 150 + os.getpid() % 80
        rclpy.init(context=self.context, domain_id=domain)
        self.hot = make_executor("events", self.context)
        self.node = DriveLifecycleNode(self.hot, context=self.context,
                                       parameter_overrides=[Parameter("config", value=str(config))])
        self.cold = SingleThreadedExecutor(context=self.context)
        self.cold.add_node(self.node)
        self.manager = rclpy.create_node("lifecycle_manager_probe", context=self.context)
        self.change = self.manager.create_client(ChangeState, f"/{NODE}/change_state")
        self.get = self.manager.create_client(GetState, f"/{NODE}/get_state")
        self.diags: list[Any] = []
        self.logs: list[Any] = []
        self.manager.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, DIAGNOSTICS_QOS)
        self.manager.create_subscription(Log, "/rosout", self.logs.append, 1000)
        self.cmd = self.manager.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
        self.hot.add_node(self.manager)
        self.spins = [SpinThread(self.hot, "test-hot"), SpinThread(self.cold, "test-lifecycle")]

    def close(self) -> None:
        self.node.release()
        for spin in self.spins:
            spin.stop(5.0)
        self.manager.destroy_node()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.sim.close()

    def call(self, client: Any, request: Any) -> Any:
        assert client.wait_for_service(timeout_sec=HANG_S)
        future = client.call_async(request)
        wait_for(future.done, HANG_S, f"{client.srv_name} answered")
        return future.result()

    def transition(self, transition_id: int) -> str:
        request = ChangeState.Request()
        request.transition.id = transition_id
        assert self.call(self.change, request).success, transition_id
        return str(self.call(self.get, GetState.Request()).current_state.label)

    def drive_system(self, since: int = 0) -> list[Any]:
        return [st for array in self.diags[since:] for st in array.status if st.name == "rovercan: drive_system"]

    def said(self, since: int, text: str, level: int = Log.INFO) -> bool:
        return any(m.name == NODE and m.level == level and text in m.msg for m in self.logs[since:])


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[Manager]:
    made = Manager(tmp_path)
    yield made
    made.close()


def level(status: Any) -> int:
    return int.from_bytes(status.level, "little") if isinstance(status.level, bytes) else int(status.level)


def test_a_manager_is_told_what_is_missing_now_and_every_transition_is_logged(manager: Manager) -> None:
    m = manager
    logs = len(m.logs)
    assert m.transition(Transition.TRANSITION_CONFIGURE) == "inactive"
    wait_for(lambda: m.said(logs, "configured: 6 drive(s) booted, not enabled"), HANG_S, "configure logged")

    # inactive: /cmd_vel refused, and the drive system says its motion held by the inactive node, at OK (a
    # state, not a failure)
    seen = len(m.diags)
    stop = Twist()  # a command to drive, refused
    stop.linear.x = 0.2

    def inactive_said() -> bool:
        m.cmd.publish(stop)
        said = m.drive_system(seen)
        return bool(said) and said[-1].message.startswith("motion held: ") and "inactive" in said[-1].message and any(
            kv.key == "held" and "inactive" in kv.value for kv in said[-1].values)

    wait_for(inactive_said, HANG_S, "the drive system's inactive on /diagnostics")
    assert all(level(st) == OK for st in m.drive_system(seen)), [(st.level, st.message) for st in m.drive_system(seen)]

    logs = len(m.logs)
    assert m.transition(Transition.TRANSITION_ACTIVATE) == "active"
    wait_for(lambda: m.said(logs, "active: motion taken; no drive enabled: call /arm"), HANG_S, "activate logged")

    # active, not armed: a /cmd_vel refusal names what is missing now
    seen, logs = len(m.diags), len(m.logs)

    def not_armed_said() -> bool:
        m.cmd.publish(stop)
        return any("/cmd_vel not applied" in st.message and "not armed" in st.message for st in m.drive_system(seen))

    wait_for(not_armed_said, HANG_S, "the refusal on /diagnostics")
    refused = [st.message for st in m.drive_system(seen) if "/cmd_vel not applied" in st.message]
    assert all("inactive" not in text and "/arm" in text and "arm:=true" in text for text in refused), refused
    def not_armed_logged() -> bool:  # a refusal is said once a second per joint: /cmd_vel keeps coming
        m.cmd.publish(stop)
        return any(x.level == Log.WARN and "refused" in x.msg and "not armed" in x.msg for x in m.logs[logs:])

    wait_for(not_armed_logged, HANG_S, "the refusal logged", lambda: str([(x.name, x.msg) for x in m.logs[logs:]]))
    warned = [x.msg for x in m.logs[logs:] if x.level == Log.WARN and "refused" in x.msg]
    assert all("inactive" not in text for text in warned), warned

    for transition, label, line in ((Transition.TRANSITION_DEACTIVATE, "inactive", "inactive: motion held; 6 drive(s)"),
                                    (Transition.TRANSITION_ACTIVATE, "active", "active: motion taken"),
                                    (Transition.TRANSITION_DEACTIVATE, "inactive", "inactive: motion held"),
                                    (Transition.TRANSITION_CLEANUP, "unconfigured", "cleaned up: 6 drive(s)")):
        logs = len(m.logs)
        assert m.transition(transition) == label
        wait_for(lambda line=line, logs=logs: m.said(logs, line), HANG_S, f"{line!r} logged")
    logs = len(m.logs)
    assert m.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN) == "finalized"
    wait_for(lambda: m.said(logs, "shut down from unconfigured"), HANG_S, "the shutdown logged")


def test_after_a_deactivate_and_an_activate_the_refusal_is_not_armed(manager: Manager) -> None:
    m = manager
    assert m.transition(Transition.TRANSITION_CONFIGURE) == "inactive"
    assert m.transition(Transition.TRANSITION_ACTIVATE) == "active"
    assert m.transition(Transition.TRANSITION_DEACTIVATE) == "inactive"
    assert m.transition(Transition.TRANSITION_ACTIVATE) == "active"
    seen = len(m.diags)
    go = Twist()
    go.linear.x = 0.2

    def refused() -> bool:
        m.cmd.publish(go)
        return any("/cmd_vel not applied" in st.message for st in m.drive_system(seen))

    wait_for(refused, HANG_S, "the refusal")
    said = [st.message for st in m.drive_system(seen) if "/cmd_vel not applied" in st.message]
    assert all("not armed" in text and "inactive" not in text for text in said), said
    logs = len(m.logs)
    assert m.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN) == "finalized"
    wait_for(lambda: m.said(logs, "shut down from active: every drive quick-stopped"), HANG_S, "the shutdown logged")

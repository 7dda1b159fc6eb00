"""The stack run's /joint_commands option (benchmarks/stack_run.py), end to end on the shipped
rover: the same ramps as one JointState a tick reach the wire as each wheel's set-points, and are
matched to what was published (a harness that matched nothing would report a set-point loss of 1
and no latency; the ratio beside it would compare nothing). The run's node is the deployed one,
run by callback_cpu.py: its command callback is /joint_commands, not a wheel's degree_cmd."""

from __future__ import annotations

import sys

import pytest

from .conftest import REPO

pytest.importorskip("rclpy")  # the stack run's publisher and the measured node are ROS 2's

sys.path.insert(0, str(REPO / "benchmarks"))
import stack_run


@pytest.mark.alone  # the shipped rover's real host timeout: beside another worker's real-time rig its drives
# stopped themselves once (host heartbeat lost, EMCY 0x8130) before the first command switched them
@pytest.mark.timeout(240)
def test_the_rover_commanded_by_joint_commands_puts_every_wheel_s_ramp_on_the_wire(
        tmp_path: object, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROVERCAN_CALLBACK_CPU", str(tmp_path / "accounts.json"))  # type: ignore[operator]
    out = stack_run.run_stack(stack_run.SHIPPED["rover"], 2.0, 100.0, ("--drive-processes",), joint_commands=True)
    assert out["commands_published"] > 0
    # set-points matched on each bus (how many is the machine's: a refusal for late data, a message
    # a keep-last-1 subscription superseded; a harness that published degrees as radians matches none)
    assert set(out["setpoint_loss_by_bus"]) == {"can0", "can1"}
    assert all(loss < 1.0 for loss in out["setpoint_loss_by_bus"].values()), out["setpoint_loss_by_bus"]
    assert out["cmd_latency_p50_ms"] is not None
    callbacks = out["cpu_by_callback"]
    assert "subscription /joint_commands" in callbacks
    assert not any(name.endswith("/degree_cmd") for name in callbacks)
    assert out["cpu_main_thread"] >= out["cpu_in_callbacks"] > 0

"""Frames lost, measured and said (motor_driver/diagnostics/frameloss.py; the driver node's /diagnostics):
per drive, the TPDOs it sends every SYNC expected against received, and its heartbeats due in
the window against received, over a window of SYNC periods; a WARN above the config's
``frame_loss_warn_percent``; the bus's figure in its status. The live test drops 5 % of the
simulated bus's frames and judges by the count of SYNCs seen, never by seconds."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_config import RoverConfig
from motor_driver import MotorDriver
from motor_driver.diagnostics.frameloss import Counts, FrameLoss, Loss, heartbeats_due, total
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def test_a_window_needs_its_syncs_then_says_what_was_lost() -> None:
    loss = FrameLoss(tpdos_per_sync=3, sync_period_s=0.01, heartbeat_period_s=0.1, window_syncs=100)
    loss.add(Counts(0.0, 0, 0, 0))
    loss.add(Counts(0.5, 50, 150, 5))
    assert loss.loss() is None and loss.progress() == "measuring (50 of 100 SYNCs)"
    loss.add(Counts(1.0, 100, 285, 7))  # 15 of 300 TPDOs lost, 2 of the 9 heartbeats due
    figure = loss.loss()
    assert figure == Loss(100, 300, 285, 9, 7)
    assert figure.text() == "TPDOs 15 of 300 lost (5.0 %), heartbeats 2 of 9 (22.2 %) over 100 SYNCs"
    assert figure.worst_percent == pytest.approx(22.2222, abs=1e-3)


@given(phase=st.floats(0.0, 0.1, exclude_max=True), start=st.floats(0.0, 5.0), span=st.floats(0.0, 5.0),
       jitter=st.lists(st.floats(-0.0499, 0.0499), min_size=200, max_size=200))
def test_a_heartbeat_none_of_which_is_lost_is_never_counted_lost(phase: float, start: float, span: float,
                                                                 jitter: list[float]) -> None:
    """Whatever the producer's phase, its jitter (under half a period) and where the window's
    ends fall, every heartbeat sent is received: none is lost; and one fewer is counted lost once
    the window holds a whole period or two: the allowance is the window's two ends, no more."""
    sent = [phase + k * 0.1 + jitter[k] for k in range(200)]
    received = sum(1 for t in sent if start < t <= start + span)
    due = heartbeats_due(span, 0.1)
    assert received >= due, (received, due)
    assert received <= due + 3


def test_the_window_slides_and_starts_again_when_not_measuring() -> None:
    loss = FrameLoss(tpdos_per_sync=2, sync_period_s=0.01, heartbeat_period_s=None, window_syncs=100)
    for k in range(0, 31):  # 10 SYNCs a sample, none lost
        loss.add(Counts(k * 0.1, k * 10, k * 20, 0))
    assert loss.loss() == Loss(100, 200, 200)  # the newest 100 SYNCs only
    loss.add(Counts(3.1, 310, 620, 0), measuring=False)  # its data went stale: the window starts again
    loss.add(Counts(3.2, 320, 640, 0))
    assert loss.loss() is None


def test_a_bus_that_shows_no_sync_is_measured_by_time() -> None:
    loss = FrameLoss(tpdos_per_sync=1, sync_period_s=0.01, heartbeat_period_s=None, window_syncs=100)
    loss.add(Counts(10.0, 0, 0, 0))
    loss.add(Counts(11.0, 0, 90, 0))  # 100 SYNC periods by the clock, 90 TPDOs
    assert loss.loss() == Loss(100, 100, 90)


def test_a_bus_figure_sums_its_drives() -> None:
    assert total([Loss(100, 300, 297), Loss(100, 300, 291, 10, 10)]) == Loss(100, 600, 588, 10, 10)
    assert total([]) is None


@pytest.mark.ros
def test_five_percent_frame_loss_is_graded_warn_within_a_bounded_count_of_syncs(driver_factory: DriverFactory) -> None:
    rclpy = pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.parameter import Parameter

    from nodes.joints.driver_node import DriverNode
    from nodes.process.qos import DIAGNOSTICS_QOS
    from nodes.process.spinning import SpinThread, make_executor

    window = 200
    sim, driver = driver_factory(make_config(1, frame_loss_window_syncs=window, frame_loss_warn_percent=2.0))
    driver.drive("joint1").enable()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=None if os.environ.get("ROS_DOMAIN_ID") else 150 + os.getpid() % 80)
    node = DriverNode(driver, context=context, parameter_overrides=[Parameter("diagnostics_rate_hz", value=10.0)])
    probe = rclpy.create_node("probe", context=context)
    diags: list[Any] = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, DIAGNOSTICS_QOS)
    hot = make_executor("events", context)
    hot.add_node(node)
    hot.add_node(probe)
    spin = SpinThread(hot, "test-hot")
    stats = driver.buses["can0"].stats

    def status(name: str) -> Any:
        return next((st for array in reversed(list(diags)) for st in array.status if st.name == name), None)

    def figure(name: str) -> str:
        st = status(name)
        return {kv.key: kv.value for kv in st.values}.get("frame_loss", "") if st is not None else ""

    try:
        wait_for(lambda: figure("rovercan: joint1").startswith("TPDOs"), 60.0, "a whole window measured")
        assert status("rovercan: joint1").level == bytes([0]), status("rovercan: joint1")  # nothing lost: OK
        assert figure("rovercan: bus can0").startswith("TPDOs")  # the bus's figure
        apply_action(sim, {"action": "frames", "channel": "can0", "drop": 0.05})
        syncs_at_drop, seen = stats.syncs, len(diags)
        wait_for(lambda: any(st.name == "rovercan: joint1" and st.message.startswith("frames lost:")
                             for array in diags[seen:] for st in array.status), 120.0, "the frame loss WARN")
        graded_after = stats.syncs - syncs_at_drop
        st = status("rovercan: joint1")
        assert st.level == bytes([1]) and "over 2 %" in st.message, st
        # a window of 200 SYNCs fills with lost frames, then a diagnostics period or two: by SYNCs, not seconds
        assert graded_after <= 3 * window, graded_after
    finally:
        apply_action(sim, {"action": "frames", "channel": "can0", "drop": 0.0})
        spin.stop(5.0)
        node.destroy_node()
        probe.destroy_node()
        rclpy.shutdown(context=context)

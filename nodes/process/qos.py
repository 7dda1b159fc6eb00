"""QoS profiles, chosen on purpose:

* commands, as published (``COMMAND_QOS``): reliable, keep last 1, volatile. Only the newest
  command matters; a late stale command must not be replayed to a moving joint (depth 1).
* commands, as the driver takes them (``SETPOINT_QOS``): best effort, keep last 1. A best-effort
  subscription takes reliable and best-effort publishers alike (a reliable one refused the
  best-effort ones); it answers no heartbeats, which at 600 commands a second was a tenth of the
  node's process (Fast DDS's event thread, docs/performance.md). A set-point stream's next
  message supersedes a lost one; a velocity stream that stops (a lost last one included) ends
  in the command watchdog's stop, a position stream holds its last target; a one-off move
  whose result matters is the ``move_joint`` action.
* state (MotorState, /joint_states, /odom): reliable, keep last ``state_qos_depth`` (10, in
  the params file), as ros2_control's joint_state_broadcaster and diff_drive_controller
  publish. A reliable publisher is read by reliable subscribers (rclpy's and RViz's default,
  Nav2) and best-effort ones alike; a best-effort one was read by nobody who kept the default
  ("offering incompatible QoS"). Keep-last never blocks the publisher: a slow subscriber
  loses the oldest samples, as it would under best effort.
* diagnostics: reliable, keep last 10, as diagnostic_aggregator expects.

The driver's own topics are created without rclpy's default QoS-event handlers (incompatible
QoS / type warnings): each is a Python waitable that the executor rebuilds into its wait set
on every wake-up, 2 per topic, 48 for 6 drives. They were measured as the largest single cost
of the node (README, Performance). The peer with the incompatible QoS still warns: its own
handlers see the same incompatibility.
"""

from __future__ import annotations

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

COMMAND_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
SETPOINT_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
STATE_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
DIAGNOSTICS_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


def state_qos(depth: int) -> QoSProfile:
    """STATE_QOS with the configured keep-last depth."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)

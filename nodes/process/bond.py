"""The managed side of a bond with a lifecycle manager: ``bond/msg/Status`` on the topic ``bond``,
as Nav2's managed nodes keep it (nav2_util's LifecycleNode: a bond made at activate, under the
node's name, heartbeats every ``bond_heartbeat_period``, its own heartbeat timeout disabled; broken
at deactivate) with bondcpp's protocol (ros/bond_core, bond.cpp):

- every heartbeat period a Status with the bond's id (the node's name), this side's instance id
  (a random UUID), ``active`` true while waiting for the other side and once it is heard;
- the other side (a Status of the same id, another instance id) heard active forms the bond; heard
  inactive (the manager broke it) ends it: one inactive Status sent back at once, then nothing;
- not formed within the connect timeout (10 s, bond's DEFAULT_CONNECT_TIMEOUT) it ends: nothing
  more is published, as bondcpp's WaitingForSister on its connect timeout;
- :meth:`BondHeartbeat.close` (deactivate, cleanup, shutdown, error) breaks it: one inactive Status
  says so, the publisher, subscription and timer go.

Nav2's lifecycle_manager (``bond_timeout`` > 0, its default 4 s) waits for the bond after each
activate and resets every node it manages when heartbeats stop for that long: a driver process
that died or hangs. Its own safety does not rest on that: each drive's host-heartbeat consumer
stops it (docs/safety.md).

The heartbeats say the node's work runs, not only its lifecycle services: where that work is on
another executor (rover_lifecycle's hot one), ``alive`` says whether it does, and a heartbeat is
withheld while it does not (a hung or starved executor), so a manager resets the nodes as it would
a Nav2 node whose executor hung.

Owner: the lifecycle node's executor thread (the timer and the subscription run there; made and
closed in its transitions, which run on that thread or under its transition lock).
"""

from __future__ import annotations

import logging
import math
import uuid
from collections.abc import Callable
from enum import Enum
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile

logger = logging.getLogger(__name__)

#: The topic of every bond (bondcpp's and Nav2's).
TOPIC = "bond"
#: bond's DEFAULT_CONNECT_TIMEOUT: how long the bond waits for the other side, s.
CONNECT_TIMEOUT_S = 10.0
#: The heartbeat timeout this side announces (nav2_util's; its own timeout is disabled there and here).
HEARTBEAT_TIMEOUT_S = 4.0


class BondState(Enum):
    WAITING = "waiting for the manager"
    ALIVE = "formed"
    DEAD = "ended"


def bond_interface() -> Any | None:
    """``bond.msg.Status``, or None where the bond interface package is not installed."""
    try:
        from bond.msg import Status
        from rclpy.type_support import check_for_type_support

        check_for_type_support(Status)  # its C type support loads (a broken build fails here, not at activate)
    except Exception as err:
        logger.debug("no bond interface: %r", err)
        return None
    return Status


class BondHeartbeat:
    """One bond of ``node`` with its lifecycle manager, heartbeats every ``period_s`` from now."""

    def __init__(self, node: Node, status_type: Any, period_s: float, alive: Callable[[], str] | None = None) -> None:
        """``alive``: "" while the node's work runs, else why not: its heartbeats are then withheld
        (a Nav2 node's bond beats on the executor that does its work, and stops with it)."""
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ValueError(f"bond heartbeat period {period_s!r} s: expected a number > 0")
        self._node = node
        self._alive = alive
        self.withheld = ""  # why the heartbeats are withheld, as said when they stopped ("" beating)
        self._status = status_type
        self.id = node.get_name()
        self.instance_id = str(uuid.uuid4())
        self.period_s = period_s
        self.state = BondState.WAITING
        self.sister = ""  # the manager's instance id, once heard
        self._waited = 0  # heartbeats sent while waiting (the connect timeout, counted in periods)
        # plain (not lifecycle) publisher: the bond is said whatever the node's state
        self._pub = Node.create_publisher(node, status_type, TOPIC, QoSProfile(depth=5))
        self._timer = node.create_timer(period_s, self._beat)
        self._sub = node.create_subscription(status_type, TOPIC, self._on_status, QoSProfile(depth=100))
        self._publish(True)

    def _publish(self, active: bool) -> None:
        msg = self._status()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.id, msg.instance_id, msg.active = self.id, self.instance_id, active
        msg.heartbeat_timeout, msg.heartbeat_period = HEARTBEAT_TIMEOUT_S, self.period_s
        self._pub.publish(msg)

    def _beat(self) -> None:
        if self.state is BondState.DEAD:
            return
        if self.state is BondState.WAITING:
            self._waited += 1
            if self._waited * self.period_s > CONNECT_TIMEOUT_S:
                self._end(f"no lifecycle manager formed it within {CONNECT_TIMEOUT_S:g} s (none uses a bond, or"
                          " its bond_timeout is 0)")
                return
        why = self._alive() if self._alive is not None else ""
        if bool(why) != bool(self.withheld):  # said once as they stop and once as they resume, not a beat
            if why:
                self._node.get_logger().error(f"bond heartbeats withheld: {why}; a lifecycle manager breaks the bond"
                                              " after its bond_timeout and resets its nodes")
            else:
                self._node.get_logger().info("bond heartbeats resumed: the driver's executor runs again")
            self.withheld = why
        if not why:
            self._publish(True)

    def _on_status(self, msg: Any) -> None:
        if msg.id != self.id or msg.instance_id == self.instance_id or self.state is BondState.DEAD:
            return
        self.sister = self.sister or msg.instance_id
        if msg.active:
            if self.state is BondState.WAITING:
                self.state = BondState.ALIVE
                self._node.get_logger().info(f"bond with the lifecycle manager formed ({TOPIC}, id {self.id})")
            return
        self._end("the lifecycle manager broke it")
        self._publish(False)  # acknowledged at once, as bondcpp does

    def _end(self, why: str) -> None:
        self.state = BondState.DEAD
        self._timer.cancel()
        self._node.get_logger().info(f"bond with the lifecycle manager ended: {why}")

    def close(self) -> None:
        """Break the bond (an inactive Status, unless it ended already) and remove its entities."""
        if self.state is not BondState.DEAD:
            self._publish(False)
            self.state = BondState.DEAD
        self._node.destroy_timer(self._timer)
        self._node.destroy_subscription(self._sub)
        self._node.destroy_publisher(self._pub)


__all__ = ["CONNECT_TIMEOUT_S", "HEARTBEAT_TIMEOUT_S", "TOPIC", "BondHeartbeat", "BondState", "bond_interface"]

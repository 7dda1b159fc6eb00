"""The bare path's subscriber, in its own process like the driver node:

    python bare_peer.py HOST PORT [N [PRIORITY]]  -> on ``bare_cmd_<i>`` (Float32, deg; i < N,
        default 1) sends one RPDO 0x301 + i; PRIORITY > 0: every thread under SCHED_FIFO at it,
        as the driver node runs (its realtime_priority), where the OS allows it

Nothing but rclpy (the EventsExecutor the node uses) and one python-can send per message;
SIGTERM ends it.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path

import can
import rclpy
from rclpy.experimental import EventsExecutor
from std_msgs.msg import Float32

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from can_config.realtime import make_process_realtime
from nodes.process import spinning
from nodes.process.qos import SETPOINT_QOS

COUNTS_PER_DEG = 4096 / 360.0
logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)


def main() -> int:
    host, port = sys.argv[1], int(sys.argv[2])
    topics = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    priority = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    if priority:
        make_process_realtime("bare_peer", priority)  # before its threads start: they inherit it
    bus = can.Bus(interface="socketcand", channel="can0", host=host, port=port, tcp_tune=True)
    spinning.init(None)
    node = rclpy.create_node("bare_peer")

    def on_cmd(cob_id: int) -> Callable[[Float32], None]:
        def send(msg: Float32) -> None:
            counts = round(msg.data * COUNTS_PER_DEG)
            bus.send(can.Message(arbitration_id=cob_id, data=b"\x3f\x00" + counts.to_bytes(4, "little", signed=True),
                                 is_extended_id=False))
        return send

    for i in range(topics):
        node.create_subscription(Float32, f"bare_cmd_{i}", on_cmd(0x301 + i), SETPOINT_QOS)
    with spinning.StopSignal() as stop:
        print("ready", flush=True)
        spinning.spin_node(node, stop.event, executor=EventsExecutor())
    bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A babbling node's cost to the driver's receive thread: a burst of EMCY frames (0x2310 from
node 1) through every listener a bus's receive thread runs for a frame (canopen's dispatch into
the drive's cache, the bus statistics, the other-master watch, the flight recorder's tap), the
driver booted on the simulator, logging on (to /dev/null, as a node's log bridge would take it).
It reports the receive thread's CPU time per EMCY and the rate one core then keeps up with; a
real bus carries about 8,000 frames/s at 1 Mbit/s.

``python benchmarks/emcy_burst.py [FRAMES]`` prints the figures as JSON.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import can  # noqa: E402

from can_config import parse_config, with_bus_overrides  # noqa: E402
from motor_driver import MotorDriver  # noqa: E402
from virtual_can import SimService  # noqa: E402

EMCY = bytes([0x10, 0x23, 0x01, 0, 0, 0, 0, 0])


def burst(frames: int) -> dict[str, float]:
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                      "kwargs": {"host": "127.0.0.1", "port": 1}}],
                           "drives": [{"name": f"joint{i}", "node_id": i, "host_timeout_ms": 500.0} for i in (1, 2)]},
                          source=REPO / "benchmarks" / "emcy_burst.yaml")
    sim = SimService.from_config(config, port=0)
    driver = MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)).start()
    try:
        listeners = driver.buses["can0"].network.listeners
        messages = [can.Message(arbitration_id=0x081, data=EMCY, is_extended_id=False, timestamp=time.time())
                    for _ in range(frames)]
        start = time.thread_time()
        for msg in messages:  # what python-can's Notifier does with each frame it received
            for listener in listeners:
                listener.on_message_received(msg)
        cpu_s = time.thread_time() - start
    finally:
        driver.close()
        sim.close()
    return {"emcy_frames": frames, "emcy_cpu_us": round(cpu_s / frames * 1e6, 2),
            "emcy_per_s_one_core": round(frames / cpu_s)}


def main() -> int:
    with open("/dev/null", "w") as sink:
        logging.basicConfig(stream=sink, level=logging.INFO)
        print(json.dumps(burst(int(sys.argv[1]) if len(sys.argv) > 1 else 10_000), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The same state run as the canopen baseline, done by rovercan's driver without ROS.
usage: driver_only.py HOST PORT N_DRIVES SYNC_MS SECONDS; prints JSON (TPDOs applied)."""

from __future__ import annotations

import json
import logging
import sys
import time

from can_config import parse_config
from motor_driver import MotorDriver

logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)


def main() -> int:
    host, port, n, sync_ms, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0", "sync_period_ms": sync_ms,
                                      "kwargs": {"host": host, "port": port}}],  # tuned by default
                           "drives": [{"name": f"j{i}", "node_id": i, "counts_per_rev": 4096} for i in range(1, n + 1)]})
    with MotorDriver(config) as driver:
        driver.start()
        print("measuring", flush=True)
        time.sleep(seconds + 1.0)
        time.sleep(1.0)  # the caller stops the drives' TPDOs meanwhile
        print(json.dumps({"received": sum(d.cache.tpdo_count for d in driver)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

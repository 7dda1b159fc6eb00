"""The baseline: the python canopen library's way (BaseNode402 + PDO callbacks) for the same
state run. usage: baseline_canopen.py HOST PORT N_DRIVES SYNC_MS SECONDS; prints JSON.

Connected as the driver's buses are by default (python-can's ``tcp_tune``): without it the
library's SYNCs leave in clumps (Nagle's algorithm, delayed ACKs; same_work.py)."""

from __future__ import annotations

import json
import sys
import time

import canopen
from baseline_canopen_rover import map_tpdos
from canopen.profiles.p402 import BaseNode402

from can_config import GENERIC_EDS


def main() -> int:
    host, port, n, sync_ms, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
    network = canopen.Network()
    network.connect(interface="socketcand", channel="can0", host=host, port=port, tcp_tune=True)
    received = [0]
    nodes = []
    for node_id in range(1, n + 1):
        node = BaseNode402(node_id, str(GENERIC_EDS))
        network.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        map_tpdos(node, received)
        node.tpdo.save()
        node.setup_402_state_machine(read_pdos=False)
        nodes.append(node)
    for node in nodes:
        node.nmt.state = "OPERATIONAL"
    network.sync.start(sync_ms / 1000.0)
    print("measuring", flush=True)
    time.sleep(seconds + 1.0)
    network.sync.stop()
    print(json.dumps({"received": received[0]}), flush=True)
    network.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""One side of the socketcand throughput benchmark, in its own process.

    python socketcand_peer.py send HOST PORT N RATE   -> sends N 8-byte frames at RATE frames/s
    python socketcand_peer.py recv HOST PORT N        -> prints received, lost, out_of_order, fps
"""

from __future__ import annotations

import json
import logging
import sys
import time

import can

logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)


def main() -> int:
    role, host, port, n = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    bus = can.Bus(interface="socketcand", channel="can0", host=host, port=port, tcp_tune=True)
    try:
        if role == "send":
            rate = float(sys.argv[5])
            print("ready", flush=True)
            sys.stdin.readline()
            start = time.perf_counter()
            for i in range(n):
                due = start + i / rate
                while time.perf_counter() < due:
                    pass
                bus.send(can.Message(arbitration_id=0x181, data=i.to_bytes(8, "little"), is_extended_id=False))
            print(json.dumps({"sent": n, "send_fps": n / (time.perf_counter() - start)}), flush=True)
        else:
            print("ready", flush=True)
            expected = 0
            out_of_order = 0
            first = None
            received = 0
            while received < n:
                msg = bus.recv(3.0)
                if msg is None:
                    break
                first = first or time.perf_counter()
                value = int.from_bytes(msg.data, "little")
                if value != expected:
                    out_of_order += 1
                expected = value + 1
                received += 1
            elapsed = time.perf_counter() - (first or time.perf_counter())
            print(json.dumps({"received": received, "lost": n - received, "out_of_order": out_of_order,
                              "recv_fps": received / elapsed if elapsed else 0.0}), flush=True)
    finally:
        bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())

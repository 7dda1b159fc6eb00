"""An independent client: the python canopen library's own BaseNode402, over python-can's
socketcand interface, in its own process. Boots a simulated drive, reaches Operation Enabled,
runs profile position to a target (or, on a drive whose 0x6502 lists no profile position but
interpolated position, streams 0x60C1:1 set-points with "enable ip mode") and checks that
0x6064 reaches it.

usage: python basenode402_pp.py HOST PORT NODE_ID EDS TARGET
prints "OK <position>" and exits 0, or prints the failure and exits 1.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

import canopen
from canopen.profiles.p402 import BaseNode402

logging.basicConfig(level=logging.ERROR)

SDO_TIMEOUT_S = 5.0


def main() -> int:
    host, port, node_id, eds, target = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
    network = canopen.Network()
    network.connect(interface="socketcand", channel="can0", host=host, port=port)
    try:
        node = BaseNode402(node_id, eds)
        network.add_node(node)
        # an SDO answer within 5 s, not the library's 0.3 s: the simulator shares a loaded CI
        # machine's two cores (an answer missed there failed this client, not the drive)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        # listen for the boot-up before sending the reset: canopen's wait_for_bootup() starts
        # listening only when called, and a quick drive's boot-up can come before that
        booted = threading.Event()
        network.subscribe(0x700 + node_id, lambda _cob, data, _t: booted.set() if data and data[0] == 0 else None)
        node.nmt.state = "RESET"
        if not booted.wait(5):
            print(f"FAIL: no boot-up of node {node_id} within 5 s of NMT reset")
            return 1
        node.setup_402_state_machine()
        for index, value in ((0x6081, 20000), (0x6083, 50000), (0x6084, 50000)):  # profile parameters
            if index in node.object_dictionary:
                try:
                    node.sdo[index].raw = value
                except canopen.SdoAbortedError as err:
                    print(f"note: 0x{index:04X} not written: {err}", file=sys.stderr)
        node.nmt.state = "OPERATIONAL"
        network.sync.start(0.01)  # synchronous TPDOs (e35's statusword) need a SYNC producer
        time.sleep(0.05)
        # the mode first: with the generic default mapping, RPDO2 carries 0x6060 *and* the
        # controlword, so switching the mode by PDO while enabled would also send controlword 0
        supported = node.sdo[0x6502].raw
        if supported & 1:
            node.op_mode = "PROFILED POSITION"
            node.state = "SWITCH ON DISABLED"
            node.state = "OPERATION ENABLED"
            node.sdo[0x607A].raw = target
            node.controlword = 0x3F  # enable operation + new setpoint + change immediately
            time.sleep(0.05)
            node.controlword = 0x0F
        elif supported >> 6 & 1:
            node.op_mode = "INTERPOLATED POSITION"
            node.state = "SWITCH ON DISABLED"
            node.state = "OPERATION ENABLED"
            node.controlword = 0x1F  # enable operation + enable ip mode
            start = node.sdo[0x6064].raw
            steps = 40
            for k in range(1, steps + 1):  # a smooth ramp of set-points, one per SYNC or so
                node.sdo[0x60C1][1].raw = start + (target - start) * k // steps
                time.sleep(0.01)
        else:
            print(f"FAIL 0x6502 = 0x{supported:08X} lists neither profile nor interpolated position")
            return 1
        deadline = time.monotonic() + 10.0
        position = node.sdo[0x6064].raw
        while abs(position - target) > 2 and time.monotonic() < deadline:
            time.sleep(0.05)
            position = node.sdo[0x6064].raw
        if abs(position - target) > 2:
            print(f"FAIL position {position} != target {target}; state {node.state}")
            return 1
        print(f"OK {position} {node.state}")
        return 0
    finally:
        network.sync.stop()
        network.disconnect()


if __name__ == "__main__":
    sys.exit(main())

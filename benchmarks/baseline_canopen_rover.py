"""The stack run's CAN work done the canopen library's way, nothing of rovercan's driver or ROS:
the config's buses (a ``canopen.Network`` each), each drive's PDOs as rovercan maps them (TPDO1
statusword + mode on change, TPDO2 position + velocity and TPDO3 torque + statusword on SYNC;
RPDO2 controlword + target position), the SYNC on every bus, every drive enabled in cyclic
synchronous position (BaseNode402) and sent the stack run's ramp (+0.1 deg a command)
by RPDO at COMMAND_HZ, 0.1 % slow as there (unwrapped: the driver takes a continuous
joint's wrap the short way, a raw CSP target would jump a turn).

    python baseline_canopen_rover.py CONFIG COMMAND_HZ SECONDS [PRIORITY]

PRIORITY > 0: every thread under SCHED_FIFO at it, as the driver node runs. Prints "measuring"
when the commands start, then (after SECONDS and one more) JSON: the TPDOs received.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import canopen
from canopen.profiles.p402 import BaseNode402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from can_config import load_config
from can_config.realtime import make_process_realtime
from motor_driver.protocol.units import Scale

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stack_run import command_rates, due

logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)

CSP = 8
TPDOS = (((0x6041, 0x6061), 255), ((0x6064, 0x606C), 1), ((0x6077, 0x6041), 1))


def map_tpdos(node: BaseNode402, received: list[int]) -> None:
    """TPDO1-3 as rovercan's driver maps them (read from the drive first), each counted in ``received[0]``."""
    node.tpdo.read()
    for n, (objects, trans_type) in enumerate(TPDOS, start=1):
        node.tpdo[n].clear()
        for index in objects:
            node.tpdo[n].add_variable(index)
        node.tpdo[n].trans_type = trans_type
        node.tpdo[n].enabled = True
        node.tpdo[n].add_callback(lambda _m: received.__setitem__(0, received[0] + 1))


def drive_node(network: canopen.Network, node_id: int, eds: Path, received: list[int]) -> tuple[BaseNode402, Any]:
    """One drive, mapped, in CSP, enabled; returns it and the target position of its RPDO2."""
    node = BaseNode402(node_id, str(eds))
    network.add_node(node)
    node.nmt.state = "PRE-OPERATIONAL"
    map_tpdos(node, received)
    node.rpdo.read()
    node.tpdo[4].enabled = False
    node.rpdo[2].clear()
    node.rpdo[2].add_variable(0x6040)
    target = node.rpdo[2].add_variable(0x607A)
    node.rpdo[2].trans_type = 255
    node.rpdo[2].enabled = True
    for n in (1, 3, 4):
        node.rpdo[n].enabled = False
    node.tpdo.save()
    node.rpdo.save()
    node.setup_402_state_machine(read_pdos=False)
    node.sdo[0x6060].raw = CSP
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x607A].raw = node.sdo[0x6064].raw  # no jump at enable
    node.state = "OPERATION ENABLED"
    node.rpdo[2][0x6040].raw = 0x0F
    return node, target


def main() -> int:
    config = load_config(Path(sys.argv[1]))
    command_hz, seconds = float(sys.argv[2]), float(sys.argv[3])
    priority = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    if priority:
        make_process_realtime("baseline_canopen_rover", priority)  # before the networks' threads: they inherit it
    received = [0]
    networks: dict[str, canopen.Network] = {}
    for bus in config.buses:
        networks[bus.name] = canopen.Network()
        networks[bus.name].connect(**bus.bus_kwargs())
    drives = []
    for d in config.drives:
        node, target = drive_node(networks[d.bus], d.node_id, d.eds, received)
        scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
        drives.append((node, target, scale))
    for bus in config.buses:
        networks[bus.name].sync.start(bus.sync_period_s)
    starts = [node.sdo[0x6064].raw for node, _, _ in drives]
    print("measuring", flush=True)
    buses = {b.name: b.sync_period_s for b in config.buses}
    loop_hz, every = command_rates([buses[d.bus] for d in config.drives], command_hz)  # as the stack run
    period = 1.001 / loop_hz
    start = next_t = time.monotonic()
    k = 0
    while time.monotonic() - start < seconds + 1.0:
        k += 1
        for i in due(k, every):
            (node, target, scale), n = drives[i], every[i]
            angle = k // n * 0.1 + 0.05  # the driver takes a wheel's 359.95 -> 0.05 the short way; a raw RPDO cannot
            target.raw = scale.deg_to_counts(angle)
            node.rpdo[2].transmit()
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    for network in networks.values():
        network.sync.stop()
    time.sleep(1.0)  # the caller stops the drives' TPDOs meanwhile
    # the work was the same only if every drive followed its commands: its position moved with the ramp
    followed = min(abs(scale.counts_to_deg(node.tpdo[2][0x6064].raw) - scale.counts_to_deg(start_counts))
                   for (node, _, scale), start_counts in zip(drives, starts, strict=True))
    print(json.dumps({"received": received[0], "followed_deg": round(followed, 1)}), flush=True)
    for network in networks.values():
        network.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The supervisor's quiet period does less, and still sees what it must: its look for another
master returns early only when nothing of one came within the hold (no bus evidence, no state
change behind this driver's back, no mark standing). A drive that another master enables by RPDO
alone (no SDO, no NMT: no bus evidence at all) is seen only through the drive's own state change,
which that early return must not skip."""

from __future__ import annotations

from collections.abc import Callable

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import make_config, wait_for

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]


def test_a_drive_enabled_by_another_masters_rpdo_alone_is_marked(sim_factory: SimFactory) -> None:
    import can

    sim, cfg = sim_factory(make_config(1))
    runner = sim.simulators["can0"]
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        bench = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:  # held by the server for its raw-mode hold, then delivered in order (never dropped)
            for cw, state in ((0x06, "READY_TO_SWITCH_ON"), (0x07, "SWITCHED_ON"), (0x0F, "OPERATION_ENABLED")):
                bench.send(can.Message(arbitration_id=0x201, data=cw.to_bytes(2, "little"), is_extended_id=False))
                wait_for(lambda state=state: runner.call(lambda: runner.drive(1).state.name) == state, 5.0, state)
            assert not driver.supervisor.handles["can0"].foreign.evidence(1, 0.0)  # nothing on the bus says it
            wait_for(lambda: "became OPERATION_ENABLED, which this driver did not command" in
                     drive.watch.foreign_master, 2.0, "the drive's own state change marked by the supervisor")
            assert not drive.snapshot().verdict.usable  # another master's drive: refused, and said why
        finally:
            bench.shutdown()

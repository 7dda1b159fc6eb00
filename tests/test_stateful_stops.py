"""A stop always wins, explored by Hypothesis: sequences of enable, disable, quick stop, velocity,
move, home and recover, each race run on a thread of its own while a stop is issued from the
test's, against the simulator, with an independent listener on the bus. After every stop
returns: no controlword with Enable Operation and no set-point of the raced command reaches the
drive (only a later, explicitly requested enable may), the simulated drive is not enabled, and
no operation is left marked busy."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import can
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from can_config import with_bus_overrides
from can_config.errors import MotorError
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import make_config, wait_for

RPDOS = (0x201, 0x301, 0x401, 0x501)  # node 1: controlword, + position, + velocity, + torque
HOST_HEARTBEAT = 0x77F  # the driver's own heartbeat (host node 127), sent on the same connection
STOP_WORDS = {0x0002, 0x0006, 0x0000}
JOIN_S = 30.0  # a hang, not a timing claim


def controlword(msg: can.Message) -> int:
    return int.from_bytes(msg.data[:2], "little")


class StopAlwaysWins(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        config = make_config(1, joint="continuous", allow_no_host_watch=False)
        self.sim = SimService.from_config(config, port=0)
        self.listener = can.Bus(interface="socketcand", channel="can0", host=self.sim.host, port=self.sim.port,
                                can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in (*RPDOS, HOST_HEARTBEAT)])
        self.driver = MotorDriver(with_bus_overrides(config, host=self.sim.host, port=self.sim.port)).start()
        self.drive = self.driver.drive("joint1")
        self.frames: list[can.Message] = []
        self.violations: list[str] = []

    def teardown(self) -> None:
        self.driver.close()
        self.listener.shutdown()
        self.sim.close()

    def _collect(self) -> None:
        """Every frame of node 1's RPDOs the driver sent so far. By order, not by a quiet moment
        (SYNC and heartbeats never stop): the driver's host heartbeat leaves on the connection its
        RPDOs use, so once two heartbeats have arrived after this call began, one of them was sent
        after it, and every RPDO sent before this call has arrived before it."""
        beats = 0
        while beats < 2:
            msg = self.listener.recv(JOIN_S)
            assert msg is not None, "no host heartbeat on the bus"
            if msg.arbitration_id == HOST_HEARTBEAT:
                beats += 1
            else:
                self.frames.append(msg)

    def _sim_state(self) -> str:
        runner = self.sim.simulators["can0"]
        return str(runner.call(lambda: runner.drive(1).state.name))

    def _quietly(self, action: Callable[[], Any]) -> None:
        try:
            action()
        except MotorError:
            pass  # refused, interrupted or timed out: the outcome is checked on the bus

    # ------------------------------------------------------------------ plain steps
    @rule()
    def enable(self) -> None:
        self._quietly(self.drive.enable)

    @rule(velocity=st.sampled_from([-60.0, 0.0, 45.0]))
    def velocity(self, velocity: float) -> None:
        self._quietly(lambda: self.drive.set_velocity(velocity))

    @rule(angle=st.sampled_from([-90.0, 30.0, 170.0]))
    def move(self, angle: float) -> None:
        self._quietly(lambda: self.drive.move_to(angle))

    @rule()
    def recover(self) -> None:
        self._quietly(self.drive.recover)

    # ------------------------------------------------------------------ the races
    @rule(action=st.sampled_from(["enable", "home", "recover", "velocity", "move"]),
          stop=st.sampled_from(["quick_stop", "disable", "disable_voltage"]))
    def race(self, action: str, stop: str) -> None:
        run: Callable[[], Any] = {
            "enable": self.drive.enable, "home": self.drive.home, "recover": self.drive.recover,
            "velocity": lambda: self.drive.set_velocity(30.0), "move": lambda: self.drive.move_to(120.0)}[action]
        self._collect()
        mark = len(self.frames)
        thread = threading.Thread(target=self._quietly, args=(run,))
        thread.start()
        if action in ("enable", "home", "recover"):  # the stop lands while the operation runs (or after it)
            wait_for(lambda: self.drive.channel.busy is not None or not thread.is_alive(), JOIN_S, f"{action} under way")
        self._quietly(getattr(self.drive, stop))
        thread.join(JOIN_S)
        assert not thread.is_alive(), f"{action} did not end"
        self._collect()
        after = self.frames[mark:]
        stops = [i for i, m in enumerate(after) if m.arbitration_id == 0x201 and controlword(m) in STOP_WORDS]
        if not stops:
            self.violations.append(f"{action} vs {stop}: no stop frame on the bus")
            return
        tail = after[stops[-1] + 1:]
        enabling = [hex(controlword(m)) for m in tail if controlword(m) & 0x0F == 0x0F]
        if enabling:
            self.violations.append(f"{action} vs {stop}: after the stop {enabling} went out")
        state = self._sim_state()
        if state == "OPERATION_ENABLED":
            self.violations.append(f"{action} vs {stop}: the drive is {state} after the stop")

    @invariant()
    def nothing_after_a_stop(self) -> None:
        assert not self.violations, self.violations

    @invariant()
    def no_stale_busy_mark(self) -> None:
        assert self.drive.channel.busy is None


StopAlwaysWins.TestCase.settings = settings(max_examples=6, stateful_step_count=8, deadline=None,
                                            suppress_health_check=[HealthCheck.too_slow])
TestStopAlwaysWins = StopAlwaysWins.TestCase

"""The bus-limit benchmark's second run (benchmarks/bus_limit.py): twelve drives on three buses,
each drive commanded at its own bus's SYNC rate, the rover's wheels at 100 Hz beside the arm at
500 Hz, by the stack run and the canopen baseline alike (stack_run.command_rates)."""

from __future__ import annotations

import sys

import yaml

from can_config import parse_config

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
from bus_limit import ARM_BUS, twelve_config_text
from stack_run import command_rates, due


def test_one_rate_for_every_drive_commands_each_on_every_tick() -> None:
    assert command_rates([0.01, 0.002], 100.0) == (100.0, [1, 1])
    assert due(7, [1, 1]) == [0, 1]


def test_each_drive_at_its_bus_sync_rate_the_loop_at_the_fastest() -> None:
    loop_hz, every = command_rates([0.01, 0.01, 0.002], 0.0)
    assert loop_hz == 500.0 and every == [5, 5, 1]
    ticks = range(1, 501)  # one second of the loop
    assert [sum(i in due(k, every) for k in ticks) for i in range(3)] == [100, 100, 500]


def test_twelve_drives_the_rover_wheels_as_shipped_beside_an_arm_bus() -> None:
    config = parse_config(yaml.safe_load(twelve_config_text()))
    rover = parse_config(yaml.safe_load((REPO / "config" / "rover.yaml").read_text()))
    assert [b.name for b in config.buses] == [b.name for b in rover.buses] + [ARM_BUS]
    assert config.drives[:6] == rover.drives
    assert [(d.bus, d.node_id) for d in config.drives[6:]] == [(ARM_BUS, i) for i in range(1, 7)]
    assert {b.name: b.sync_period_s for b in config.buses} == {"can0": 0.01, "can1": 0.01, ARM_BUS: 0.002}

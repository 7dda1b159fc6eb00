"""Scenarios do what they say: the examples of virtual_can/scenario.py's docstring, parsed from it
and played against the simulator; ``on`` read as the word it is; a step that is not one refused
with its line."""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import pytest

from can_config import GENERIC_EDS, load_drive_od
from can_config.errors import ConfigError
from virtual_can import SimDriveSpec, SimService, scenario
from virtual_can.scenario import apply_action, load_scenario
from virtual_can.sim import SimulatedDrive

#: A hang bound: the simulator answers within it whatever the load.
HANG_S = 10.0


def docstring_scenario(tmp_path: Path) -> Path:
    """The module docstring's example, as a scenario file."""
    doc = scenario.__doc__ or ""
    block = doc[doc.index("    steps:"):doc.index("\n\n", doc.index("    steps:"))]
    path = tmp_path / "docstring.yaml"
    path.write_text(textwrap.dedent(block) + "\n")
    return path


@pytest.fixture
def sim() -> Iterator[SimService]:
    """Every drive the docstring names: nodes 1 to 3 on can0, node 2 on can1."""
    service = SimService([SimDriveSpec(1), SimDriveSpec(2), SimDriveSpec(3), SimDriveSpec(2, channel="can1")], port=0)
    yield service
    service.close()


def _model(sim: SimService, step: dict[str, Any]) -> Any:
    """What the step's drive (or channel) now holds, read on its simulator's thread."""
    if step["action"] == "frames":
        return sim.engine.channel(step.get("channel", "can0")).faults
    if "node" not in step:  # every drive of its channel (sync_answer)
        simulator = sim.simulators[step["channel"]]
        return [simulator.call(lambda d=d: _copy(d)) for d in simulator.drives.values()]
    simulator = sim.simulator_for(step["node"], step.get("channel"))
    drive = simulator.drive(step["node"])
    return simulator.call(lambda: _copy(drive))


def _copy(drive: SimulatedDrive) -> dict[str, Any]:
    faults = drive.faults
    return {"unplugged": faults.unplugged, "tpdo_silent": faults.tpdo_silent, "tx_dead": faults.tx_dead,
            "guard_toggle_stuck": faults.guard_toggle_stuck, "heartbeat_deaf": faults.heartbeat_deaf,
            "sto_low": faults.sto_low, "sdo_delay_s": faults.sdo_delay_s, "force_abort": drive.sdo.force_abort,
            "enable_step_delay_s": faults.enable_step_delay_s, "ack_delay_max_s": faults.ack_delay_max_s,
            "stalled": faults.stalled, "load_nm": drive.params.load_nm, "off": faults.power_off_until > 0,
            "statusword": drive.statusword, "reset_at_writes": list(faults.reset_at_writes),
            "reset_at_object": faults.reset_at_object, "reset_answers": faults.reset_answers,
            "sync_answer": (faults.sync_delay_s, faults.sync_jitter_s), "lost_tpdos": faults.lost_tpdos,
            "quick_stop_option": drive.quick_stop_option, "speed_reached_in_quick_stop": faults.speed_reached_in_quick_stop}


#: What each action's step must leave in the model: a check of (model, step).
EFFECTS: dict[str, Callable[[Any, dict[str, Any]], bool]] = {
    "unplug": lambda m, s: m["unplugged"],
    "plug": lambda m, s: not m["unplugged"],
    "power_cycle": lambda m, s: m["off"],
    "fault": lambda m, s: m["statusword"] & 0x4F == 0x08,
    "sto": lambda m, s: m["sto_low"] == s["low"],
    "frames": lambda f, s: (f.drop, f.delay, f.corrupt) == (s["drop"], s["delay"], s["corrupt"]),
    "sdo": lambda m, s: m["sdo_delay_s"] == s.get("delay_s", 0.0) and m["force_abort"] == s.get("abort"),
    "disconnect_clients": lambda m, s: True,
    "tpdos": lambda m, s: m["tpdo_silent"] is not s["on"],
    "slow_enable": lambda m, s: m["enable_step_delay_s"] == s["delay_s"],
    "slow_ack": lambda m, s: m["ack_delay_max_s"] == s["max_s"],
    "load": lambda m, s: m["load_nm"] == s["nm"] if "nm" in s else m["stalled"] == s["stall"],
    "tx_dead": lambda m, s: m["tx_dead"] is s["on"],
    "tpdo_lost": lambda m, s: (s["cob_id"] in m["lost_tpdos"]) is s.get("on", True),
    "heartbeat_deaf": lambda m, s: m["heartbeat_deaf"] is s["on"],
    "guard_toggle_stuck": lambda m, s: m["guard_toggle_stuck"] is s["on"],
    "sdo_reset": lambda m, s: (m["reset_at_writes"] == list(s.get("at_writes", []))
                               and m["reset_at_object"] == ((s["index"], s.get("subindex")) if "index" in s else None)
                               and m["reset_answers"] == s.get("answer", True)),
    "quick_stop_option": lambda m, s: m["quick_stop_option"] == s["option"],
    "speed_reached_in_quick_stop": lambda m, s: m["speed_reached_in_quick_stop"] is s["on"],
    "sync_answer": lambda m, s: all(d["sync_answer"] == (s.get("delay_s", 0.0), s.get("jitter_s", 0.0))
                                    for d in (m if isinstance(m, list) else [m])),
}


def test_every_docstring_example_does_what_it_says(tmp_path: Path, sim: SimService) -> None:
    steps = load_scenario(docstring_scenario(tmp_path))
    assert {s["action"] for s in steps} == set(scenario.ACTIONS), "the docstring shows every action"
    for step in steps:
        assert all(isinstance(key, str) for key in step), f"line {step}: a key read as something else"
        apply_action(sim, step)
        model = None if step["action"] == "disconnect_clients" else _model(sim, step)
        assert EFFECTS[step["action"]](model, step), f"{dict(step)} left {model}"


class _Tpdos:
    """A canopen client of node 2 on can1: its TPDO1 sent at each SYNC, and counted."""

    def __init__(self, sim: SimService) -> None:
        self.network = canopen.Network(can.Bus(interface="socketcand", channel="can1", host=sim.host, port=sim.port))
        self.network.connect()
        self.node = self.network.add_node(2, load_drive_od(GENERIC_EDS, 2))
        self.seen = 0
        self.network.subscribe(0x182, self._count)
        self.node.sdo[0x1800][2].raw = 1  # TPDO1 at every SYNC
        self.network.send_message(0x000, bytes([0x01, 2]))  # NMT start

    def _count(self, cob: int, data: bytearray, timestamp: float) -> None:
        self.seen += 1

    def after_syncs(self, n: int) -> int:
        """TPDO1s that answered ``n`` SYNCs: each SYNC is followed by an SDO read of the same drive,
        whose answer leaves it after any TPDO that SYNC made (one simulator thread, one order)."""
        before = self.seen
        for _ in range(n):
            self.network.send_message(0x080, b"")
            self.node.sdo.upload(0x6041, 0)
        return self.seen - before

    def close(self) -> None:
        self.network.disconnect()


def test_on_true_restores_the_tpdos(tmp_path: Path, sim: SimService) -> None:
    """``{action: tpdos, on: false}`` silences them and ``on: true`` brings them back, as written
    in the docstring (YAML 1.1 read the key ``on`` as True: both silenced them for good)."""
    steps = [s for s in load_scenario(docstring_scenario(tmp_path)) if s["action"] == "tpdos"]
    assert [s["on"] for s in steps] == [False, True]
    client = _Tpdos(sim)
    try:
        assert client.after_syncs(3) == 3
        apply_action(sim, steps[0])
        assert client.after_syncs(3) == 0
        apply_action(sim, steps[1])
        assert client.after_syncs(3) == 3
    finally:
        client.close()


@pytest.mark.parametrize(("step", "refusal"), [
    ("{at_s: 1, node: 1, action: tpdos, onn: true}", r"line 3\).*tpdos takes no key 'onn'; its keys are at_s,"
                                                      r" action, node, channel, on"),
    ("{at_s: 1, node: 1, action: tpdoss}", r"line 3\).*action 'tpdoss' is not a scenario action; use one of unplug"),
    ("{at_s: 1, node: 1, action: tpdos, on: yes}", r"line 3\).*tpdos's on is 'yes'; give true or false"),
    ("{at_s: 1, action: frames, node: 1}", r"line 3\).*frames takes no key 'node'"),
    ("{at_s: soon, node: 1, action: plug}", r"line 3\).*plug's at_s is 'soon'; give a number"),
    ("{at_s: 1, channel: can1, action: sync_answer, delay_s: 2}",
     r"line 3\).*sync_answer's delay_s is 2.0; give 0 to 1.0 s"),
    ("{at_s: 1, channel: can1, action: sync_answer, jitter_s: -0.01}",
     r"line 3\).*sync_answer's jitter_s is -0.01; give 0 to 1.0 s"),
])
def test_a_step_that_is_not_one_is_refused_with_its_line(tmp_path: Path, step: str, refusal: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(f"steps:\n  - {{at_s: 0.5, node: 1, action: unplug}}\n  - {step}\n")
    with pytest.raises(ConfigError, match=refusal):
        load_scenario(path)


def test_python_steps_are_checked_too(sim: SimService) -> None:
    with pytest.raises(ConfigError, match="tpdos takes no key True"):
        apply_action(sim, {"action": "tpdos", "node": 1, True: False})

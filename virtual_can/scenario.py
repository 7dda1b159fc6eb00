"""Fault-injection scenarios from YAML, played against a running :class:`SimService`.

    steps:
      - {at_s: 2.0, node: 1, action: unplug}
      - {at_s: 3.0, node: 1, action: plug}
      - {at_s: 4.0, node: 2, action: power_cycle, off_s: 0.5}
      - {at_s: 5.0, node: 3, action: fault, code: 0x2310}
      - {at_s: 6.0, node: 3, action: sto, low: true}
      - {at_s: 7.0, channel: can0, action: frames, drop: 0.01, delay: 0.0, corrupt: 0.0}
      - {at_s: 8.0, node: 1, action: sdo, delay_s: 0.2}
      - {at_s: 9.0, node: 1, action: sdo, abort: 0x08000022}
      - {at_s: 10.0, action: disconnect_clients}
      - {at_s: 11.0, node: 2, channel: can1, action: tpdos, on: false}
      - {at_s: 12.0, node: 1, action: slow_enable, delay_s: 0.7}
      - {at_s: 13.0, node: 1, action: slow_ack, max_s: 0.004}
      - {at_s: 14.0, node: 1, action: load, nm: 0.05}      # a slope: motor-side load torque
      - {at_s: 15.0, node: 1, action: load, stall: true}   # the wheel jams: the shaft cannot turn
      - {at_s: 16.0, node: 1, action: sdo_reset, at_writes: [15, 4]}  # resets at the 15th SDO write, again 4 later
      - {at_s: 17.0, node: 1, action: sdo_reset, index: 0x1600, subindex: 0, answer: false}
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.textfile import load_yaml
from virtual_can.service import SimService
from virtual_can.sim import SimulatedDrive

logger = logging.getLogger(__name__)

ACTIONS = ("unplug", "plug", "power_cycle", "fault", "sto", "tpdos", "slow_enable", "slow_ack", "frames", "sdo",
           "disconnect_clients", "load", "tx_dead", "guard_toggle_stuck", "heartbeat_deaf", "sdo_reset")


def _channel_faults(sim: SimService, step: Mapping[str, Any]) -> None:
    """The ``frames`` action: drop, delay and corrupt frames on a channel."""
    chan = sim.engine.channel(str(step.get("channel", "can0")))
    chan.faults.drop = float(step.get("drop", 0.0))
    chan.faults.delay = float(step.get("delay", 0.0))
    chan.faults.delay_s = float(step.get("delay_s", chan.faults.delay_s))
    chan.faults.corrupt = float(step.get("corrupt", 0.0))


def _arm_sdo_reset(drive: SimulatedDrive, step: Mapping[str, Any]) -> None:
    """The ``sdo_reset`` action: ``at_writes`` (a count, or counts each after the reset before),
    or ``index`` (and ``subindex``); ``answer``: the write is answered before the reset;
    ``bootup``: the boot-up frame goes out (False: it is lost). Given neither count nor index,
    the armed resets are cleared."""
    faults = drive.faults
    at = step.get("at_writes", [])
    faults.reset_at_writes = [int(n) for n in (at if isinstance(at, list) else [at])]
    if any(n < 1 for n in faults.reset_at_writes):
        raise ConfigError(f"sdo_reset at_writes {at!r}: each count is 1 or more (1: the next write)")
    index, sub = step.get("index"), step.get("subindex")
    faults.reset_at_object = (int(index), int(sub) if sub is not None else None) if index is not None else None
    faults.reset_answers = bool(step.get("answer", True))
    faults.reset_bootup = bool(step.get("bootup", True))
    faults.reset_pending = False


def _drive_action(drive: SimulatedDrive, action: str, step: Mapping[str, Any]) -> None:
    """One drive's fault switch, on its simulator's thread."""
    now = time.monotonic()
    if action in ("unplug", "plug"):
        drive.faults.unplugged = action == "unplug"
    elif action == "power_cycle":
        drive.power_cycle(now, float(step.get("off_s", 0.5)))
    elif action == "fault":
        drive.raise_fault(int(step.get("code", 0x1000)))
    elif action == "tpdos":  # the drive stops (or resumes) sending its TPDOs; heartbeat and SDO go on
        drive.faults.tpdo_silent = not bool(step.get("on", False))
    elif action == "tx_dead":  # it hears and obeys, sends nothing (a broken TX line); on: false heals it
        drive.faults.tx_dead = bool(step.get("on", True))
    elif action == "guard_toggle_stuck":  # its node-guarding answers keep toggle bit 0
        drive.faults.guard_toggle_stuck = bool(step.get("on", True))
    elif action == "heartbeat_deaf":  # it stops hearing heartbeats (its RX filter, a stalled host): its host watch trips
        drive.faults.heartbeat_deaf = bool(step.get("on", True))
    elif action == "slow_enable":  # each enabling transition takes delay_s
        drive.faults.enable_step_delay_s = float(step.get("delay_s", 0.0))
    elif action == "slow_ack":  # the set-point acknowledge comes 0..max_s late
        drive.faults.ack_delay_max_s = float(step.get("max_s", 0.0))
    elif action == "load":  # external load torque (motor side) and/or a blocked shaft
        if "nm" in step:
            drive.params.load_nm = float(step["nm"])
        drive.faults.stalled = bool(step.get("stall", False))
    elif action == "sto":
        drive.faults.sto_low = bool(step.get("low", True))
    elif action == "sdo_reset":  # it resets itself at the n-th SDO write from now, or at a write to an object
        _arm_sdo_reset(drive, step)
    elif action == "sdo":
        drive.faults.sdo_delay_s = float(step.get("delay_s", 0.0))
        abort = step.get("abort")
        drive.sdo.force_abort = int(abort) if abort is not None else None


def apply_action(sim: SimService, step: Mapping[str, Any]) -> None:
    """Apply one fault-injection step (also used directly from Python)."""
    action = step.get("action")
    if action not in ACTIONS:
        raise ConfigError(f"scenario action {action!r}: expected one of {', '.join(ACTIONS)}")
    if action == "disconnect_clients":
        sim.server.disconnect_clients()
        return
    if action == "frames":
        _channel_faults(sim, step)
        return
    node = int(step.get("node", 0))
    channel = step.get("channel")
    simulator = sim.simulator_for(node, str(channel) if channel is not None else None)
    drive = simulator.drive(node)

    simulator.call(lambda: _drive_action(drive, str(action), step))


def load_scenario(path: str | Path) -> list[dict[str, Any]]:
    data = load_yaml(Path(path), "scenario")
    steps = data.get("steps") if isinstance(data, dict) else None
    if not isinstance(steps, list):
        raise ConfigError(f"{path}: expected a mapping with a 'steps' list")
    for i, step in enumerate(steps):
        if not isinstance(step, dict) or step.get("action") not in ACTIONS:
            raise ConfigError(f"{path}: steps[{i}]: expected a mapping with action one of {', '.join(ACTIONS)}")
    return sorted(steps, key=lambda s: float(s.get("at_s", 0.0)))


def run_scenario_in_background(sim: SimService, path: str | Path, stop: threading.Event) -> threading.Thread:
    return run_steps_in_background(sim, load_scenario(path), stop)


def run_steps_in_background(sim: SimService, steps: list[dict[str, Any]], stop: threading.Event) -> threading.Thread:
    """Play ``steps`` (sorted by ``at_s``) from now, in a thread, until ``stop``."""

    def run() -> None:
        start = time.monotonic()
        for step in steps:
            if stop.wait(max(0.0, start + float(step.get("at_s", 0.0)) - time.monotonic())):
                return
            logger.warning("scenario: %s", dict(step))
            try:
                apply_action(sim, step)
            except Exception as err:
                logger.error("scenario step %s failed: %s", step, err)

    thread = threading.Thread(target=run, daemon=True, name="virtual_can-scenario")
    thread.start()
    return thread

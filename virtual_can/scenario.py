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
      - {at_s: 11.0, node: 2, channel: can1, action: tpdos, on: false}   # its TPDOs stop
      - {at_s: 11.5, node: 2, channel: can1, action: tpdos, on: true}    # and come again
      - {at_s: 11.7, node: 2, channel: can1, action: tpdo_lost, cob_id: 0x282}   # that TPDO alone stops
      - {at_s: 11.8, node: 2, channel: can1, action: tpdo_lost, cob_id: 0x282, on: false}
      - {at_s: 12.0, node: 1, action: slow_enable, delay_s: 0.7}
      - {at_s: 13.0, node: 1, action: slow_ack, max_s: 0.004}
      - {at_s: 14.0, node: 1, action: load, nm: 0.05}      # a slope: motor-side load torque
      - {at_s: 15.0, node: 1, action: load, stall: true}   # the wheel jams: the shaft cannot turn
      - {at_s: 16.0, node: 1, action: tx_dead, on: true}   # it hears and obeys, sends nothing
      - {at_s: 17.0, node: 1, action: tx_dead, on: false}
      - {at_s: 18.0, node: 1, action: heartbeat_deaf, on: true}
      - {at_s: 19.0, node: 1, action: heartbeat_deaf, on: false}
      - {at_s: 20.0, node: 1, action: guard_toggle_stuck, on: true}
      - {at_s: 21.0, node: 1, action: guard_toggle_stuck, on: false}
      - {at_s: 16.0, node: 1, action: sdo_reset, at_writes: [15, 4]}  # resets at the 15th SDO write, again 4 later
      - {at_s: 17.0, node: 1, action: sdo_reset, index: 0x1600, subindex: 0, answer: false}
      - {at_s: 18.0, channel: can1, action: sync_answer, delay_s: 0.03}   # every drive of can1 answers SYNC 30 ms late
      - {at_s: 19.0, node: 2, channel: can0, action: sync_answer, delay_s: 0.005, jitter_s: 0.02}  # 5-25 ms, in order
      - {at_s: 20.0, node: 1, action: quick_stop_option, option: 6}   # its firmware's: stays in Quick Stop Active
      - {at_s: 21.0, node: 1, action: speed_reached_in_quick_stop, on: true}   # bit 10 set through the ramp

A scenario's keys are read as written: only ``true`` and ``false`` are booleans (YAML 1.2), so
``on`` and ``off`` (YAML 1.1's booleans, which PyYAML reads as such) are plain words here and
``on: false`` means what it says. A step with a key its action does not take, a value of the
wrong kind, or an unknown action is refused with its line and what the action allows
(:data:`ACTION_KEYS`). Steps are played on a thread of their own (``virtual_can-scenario``),
each handed to its drive simulator's thread (``DriveSimulator.call``).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from can_config.errors import ConfigError
from can_config.textfile import StrictLoader, load_yaml
from virtual_can.service import SimService
from virtual_can.sim import SimulatedDrive

logger = logging.getLogger(__name__)

#: The keys every step may have besides its action's own: when (seconds from the start) and what.
COMMON_KEYS: dict[str, type] = {"at_s": float, "action": str}
_DRIVE: dict[str, type] = {"node": int, "channel": str}
_SWITCH: dict[str, type] = {**_DRIVE, "on": bool}
#: Each action's own keys and the kind of value each takes (float: any number).
ACTION_KEYS: dict[str, dict[str, type]] = {
    "unplug": _DRIVE, "plug": _DRIVE, "power_cycle": {**_DRIVE, "off_s": float},
    "fault": {**_DRIVE, "code": int, "latched": bool}, "sto": {**_DRIVE, "low": bool}, "tpdos": _SWITCH,
    "slow_enable": {**_DRIVE, "delay_s": float}, "slow_ack": {**_DRIVE, "max_s": float},
    "frames": {"channel": str, "drop": float, "delay": float, "delay_s": float, "corrupt": float},
    "sdo": {**_DRIVE, "delay_s": float, "abort": int}, "disconnect_clients": {},
    "load": {**_DRIVE, "nm": float, "stall": bool}, "tx_dead": _SWITCH, "guard_toggle_stuck": _SWITCH,
    "heartbeat_deaf": _SWITCH, "tpdo_lost": {**_SWITCH, "cob_id": int},
    "sdo_reset": {**_DRIVE, "at_writes": list, "index": int, "subindex": int, "answer": bool, "bootup": bool},
    "sync_answer": {**_DRIVE, "delay_s": float, "jitter_s": float},
    "quick_stop_option": {**_DRIVE, "option": int}, "speed_reached_in_quick_stop": _SWITCH}
ACTIONS = tuple(ACTION_KEYS)
#: ``sync_answer``'s delay and jitter (s): a synchronous TPDO is due within its SYNC period (CiA 301's
#: synchronous window); a second covers any SYNC period this project configures
SYNC_ANSWER_MAX_S = 1.0
_KIND_NAMES = {float: "a number", int: "a whole number", bool: "true or false", str: "a name",
               list: "a whole number or a list of them"}


def _is_kind(value: object, kind: type) -> bool:
    if isinstance(value, bool):
        return kind is bool
    if kind is float:
        return isinstance(value, (int, float))
    if kind is list:  # one count or several
        return all(isinstance(v, int) and not isinstance(v, bool) for v in (value if isinstance(value, list) else [value]))
    return isinstance(value, kind)


def check_step(step: Mapping[Any, Any], where: str = "scenario step") -> None:
    """Refuse a step whose action is unknown, or with a key its action does not take or a value
    of the wrong kind, naming ``where`` (the file and line) and what is allowed."""
    action = step.get("action")
    if not isinstance(action, str) or action not in ACTION_KEYS:
        raise ConfigError(f"{where}: action {action!r} is not a scenario action; use one of {', '.join(ACTIONS)}")
    allowed = {**COMMON_KEYS, **ACTION_KEYS[action]}
    for key, value in step.items():
        if key not in allowed:
            raise ConfigError(f"{where}: {action} takes no key {key!r}; its keys are {', '.join(allowed)}")
        if not _is_kind(value, allowed[key]):
            raise ConfigError(f"{where}: {action}'s {key} is {value!r}; give {_KIND_NAMES[allowed[key]]}")
    if action == "sync_answer":
        _sync_answer(step, where)
    if action == "quick_stop_option":
        _quick_stop_option(step, where)


class _Step(dict[Any, Any]):
    """A mapping of a scenario file, with the line it starts on (1-based)."""

    line = 0


class _ScenarioLoader(StrictLoader):
    """The config files' loader with YAML 1.2's booleans (``true``, ``false``): YAML 1.1's ``on``,
    ``off``, ``yes`` and ``no`` stay words, so a step's key ``on`` is ``"on"``. Each mapping is a
    :class:`_Step` that knows its line."""


_BOOL_TAG = "tag:yaml.org,2002:bool"
_ScenarioLoader.yaml_implicit_resolvers = {
    first: [(tag, pattern) for tag, pattern in resolvers if tag != _BOOL_TAG]
    for first, resolvers in StrictLoader.yaml_implicit_resolvers.items()}
_ScenarioLoader.add_implicit_resolver(_BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))


def _located_mapping(loader: _ScenarioLoader, node: yaml.MappingNode) -> _Step:
    mapping = _Step(StrictLoader.yaml_constructors[yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG](loader, node))
    mapping.line = node.start_mark.line + 1
    return mapping


_ScenarioLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _located_mapping)


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


#: switches that are on unless ``on: false``, each the drive's Faults field of its name: tx_dead (it
#: hears and obeys, sends nothing: a broken TX line), guard_toggle_stuck (its node-guarding answers
#: keep toggle bit 0), heartbeat_deaf (it stops hearing heartbeats: its RX filter, a stalled host;
#: its host watch trips), speed_reached_in_quick_stop (a velocity mode's bit 10 stays set through its
#: quick-stop ramp, as some vendors' drives keep "speed reached")
_ON_SWITCHES = ("tx_dead", "guard_toggle_stuck", "heartbeat_deaf", "speed_reached_in_quick_stop")
#: the quick-stop options (0x605A) the model has: 1-4 (a ramp, then Switch On Disabled), 5-8 (a ramp,
#: then held in Quick Stop Active); the current (3, 7) and voltage (4, 8) limits brake on the quick-stop
#: ramp; 0 (the power stage off at once: the shaft coasts) is not modelled
QUICK_STOP_OPTIONS = (1, 2, 3, 4, 5, 6, 7, 8)


def _sync_answer(step: Mapping[str, Any], where: str = "sync_answer") -> tuple[float, float]:
    """The ``sync_answer`` action's (delay_s, jitter_s), each checked against its range."""
    values = []
    for key in ("delay_s", "jitter_s"):
        value = float(step.get(key, 0.0))
        if not 0.0 <= value <= SYNC_ANSWER_MAX_S:
            raise ConfigError(f"{where}: sync_answer's {key} is {value!r}; give 0 to {SYNC_ANSWER_MAX_S} s"
                              " (a late answer within the SYNC period; 0: at once)")
        values.append(value)
    return values[0], values[1]


#: the slow drive's actions: each its Faults field and the step's key that sets it (slow_enable: each
#: enabling transition takes delay_s; slow_ack: the set-point acknowledge comes 0..max_s late)
_SLOW = {"slow_enable": ("enable_step_delay_s", "delay_s"), "slow_ack": ("ack_delay_max_s", "max_s")}


def _quick_stop_option(step: Mapping[str, Any], where: str = "quick_stop_option") -> int:
    option = int(step.get("option", 2))
    if option not in QUICK_STOP_OPTIONS:
        raise ConfigError(f"{where}: quick_stop_option's option is {option!r}; give one of"
                          f" {', '.join(map(str, QUICK_STOP_OPTIONS))} (CiA 402's 0x605A; 0 is not modelled)")
    return option


def _silence_tpdos(drive: SimulatedDrive, action: str, step: Mapping[str, Any]) -> None:
    """``tpdos``: the drive stops (``on: false``) or resumes sending its TPDOs, heartbeat and SDO going
    on; ``tpdo_lost``: the TPDO ``cob_id`` alone no longer leaves it (a mapping lost, a PDO dropped;
    ``on: false`` heals it)."""
    faults = drive.faults
    if action == "tpdos":
        faults.tpdo_silent = not bool(step.get("on", False))
        return
    cob_id = int(step["cob_id"])
    faults.lost_tpdos = faults.lost_tpdos | {cob_id} if step.get("on", True) else faults.lost_tpdos - {cob_id}


def _drive_action(drive: SimulatedDrive, action: str, step: Mapping[str, Any]) -> None:
    """One drive's fault switch, on its simulator's thread."""
    now = time.monotonic()
    if action in ("unplug", "plug"):
        drive.faults.unplugged = action == "unplug"
    elif action == "power_cycle":
        drive.power_cycle(now, float(step.get("off_s", 0.5)))
    elif action == "fault":  # latched: in the cycle of the next SYNC, after its TPDOs latched (Faults.latched_fault)
        code = int(step.get("code", 0x1000))
        if step.get("latched", False):
            drive.faults.latched_fault = code
        else:
            drive.raise_fault(code)
    elif action in ("tpdos", "tpdo_lost"):
        _silence_tpdos(drive, action, step)
    elif action in _ON_SWITCHES:  # on: false heals it
        setattr(drive.faults, action, bool(step.get("on", True)))
    elif action in _SLOW:
        field, key = _SLOW[action]
        setattr(drive.faults, field, float(step.get(key, 0.0)))
    elif action == "load":  # external load torque (motor side) and/or a blocked shaft
        if "nm" in step:
            drive.params.load_nm = float(step["nm"])
        drive.faults.stalled = bool(step.get("stall", False))
    elif action == "sto":
        drive.faults.sto_low = bool(step.get("low", True))
    elif action == "sdo_reset":  # it resets itself at the n-th SDO write from now, or at a write to an object
        _arm_sdo_reset(drive, step)
    elif action == "sync_answer":  # its synchronous TPDOs leave delay_s (+ 0..jitter_s) after the SYNC, in order
        drive.faults.sync_delay_s, drive.faults.sync_jitter_s = _sync_answer(step)
    elif action == "quick_stop_option":  # fixed by its firmware: what 0x605A says is not what it does
        drive.faults.quick_stop_option = _quick_stop_option(step)
    elif action == "sdo":
        drive.faults.sdo_delay_s = float(step.get("delay_s", 0.0))
        abort = step.get("abort")
        drive.sdo.force_abort = int(abort) if abort is not None else None


def apply_action(sim: SimService, step: Mapping[str, Any]) -> None:
    """Apply one fault-injection step (also used directly from Python)."""
    check_step(step)
    action = step["action"]
    if action == "disconnect_clients":
        sim.server.disconnect_clients()
        return
    if action == "frames":
        _channel_faults(sim, step)
        return
    node = int(step.get("node", 0))
    channel = step.get("channel")
    if action == "sync_answer" and "node" not in step:  # every drive of the channel (a busy bus)
        if channel is None:
            raise ConfigError("sync_answer without a node needs its channel (every drive of it answers late)")
        bus_sim = sim.simulators.get(str(channel))
        if bus_sim is None:
            raise ConfigError(f"sync_answer: no simulated drives on channel {channel!r}; have {', '.join(sim.simulators)}")
        delay_s, jitter_s = _sync_answer(step)

        def answer_late() -> None:
            for each in bus_sim.drives.values():
                each.faults.sync_delay_s, each.faults.sync_jitter_s = delay_s, jitter_s

        bus_sim.call(answer_late)
        return
    simulator = sim.simulator_for(node, str(channel) if channel is not None else None)
    drive = simulator.drive(node)

    simulator.call(lambda: _drive_action(drive, str(action), step))


def load_scenario(path: str | Path) -> list[dict[str, Any]]:
    """A scenario file's steps, sorted by ``at_s``; :class:`ConfigError` naming the step's line
    and what its action allows for a step that is not one."""
    data = load_yaml(Path(path), "scenario", _ScenarioLoader)
    steps = data.get("steps") if isinstance(data, dict) else None
    if not isinstance(steps, list):
        raise ConfigError(f"{path}: expected a mapping with a 'steps' list")
    for i, step in enumerate(steps):
        where = f"{path}: steps[{i}]" + (f" (line {step.line})" if isinstance(step, _Step) else "")
        if not isinstance(step, dict):
            raise ConfigError(f"{where}: expected a mapping such as {{at_s: 1.0, node: 1, action: unplug}}")
        check_step(step, where)
    return sorted(steps, key=lambda s: float(s.get("at_s", 0.0)))


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

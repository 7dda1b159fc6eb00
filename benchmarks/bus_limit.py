"""The bus at its limit (issue 55): six drives on one bus at 500 Hz CSP, measured as the rover's
stack run is (stack_run.run_stack: driver + ROS node in its own process, the simulator with each
bus's drive models in processes of their own, an independent listener) beside the canopen library
doing the same work (same_work.baseline_same_work).

The config is generated from config/rover.yaml's wheel settings: six drives (nodes 1-6) on can0,
SYNC every 2 ms, every joint commanded at 500 Hz. Per cycle: one SYNC, six RPDOs (6 bytes), six
TPDO2 (8 bytes) and six TPDO3 (4 bytes): 19 frames, 9,500 frames/s, 88 % of 1 Mbit/s without bit
stuffing (106 % with the worst case). The config declares ``bitrate: 2000000``: the driver's
planner (motor_driver/bus/load.py) counts each drive's event TPDO1 every SYNC and worst-case
stuffing, 132 % of 1 Mbit/s, and refuses the config; the simulator does not model wire time, and
the load reported here is the traffic measured at the listener over 1 Mbit/s.

The second run (keys ``bus_limit_12_*``): twelve drives on three buses, config/rover.yaml's six
wheels on can0 and can1 (SYNC every 10 ms, each commanded at 100 Hz) beside the six drives above
moved to ``can2`` (500 Hz); whether the emulator carried it is judged on can2's listener.

``python benchmarks/bus_limit.py [SECONDS] [--six | --twelve]`` prints the figures as JSON.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

# a DDS domain of its own unless one is set (run.py's reason: another graph's /diagnostics and topics)
os.environ.setdefault("ROS_DOMAIN_ID", str(70 + os.getpid() % 30))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import stack_run
from stack_run import REPO, is_tpdo

sys.path.insert(0, str(REPO))
from can_config.bits import frame_bits

HZ = 500.0
DRIVES = 6
WIRE_BITRATE = 1_000_000
WHEEL_KEYS = ("counts_per_rev", "gear_ratio", "max_velocity_deg_s", "profile_acceleration_deg_s2", "position_mode")


def config_text(drives: int = DRIVES, hz: float = HZ, bitrate: int = 2 * WIRE_BITRATE) -> str:
    """``drives`` drives on one bus (can0) with config/rover.yaml's wheel settings, SYNC at ``hz``."""
    rover = yaml.safe_load((REPO / "config" / "rover.yaml").read_text())
    wheel = {k: rover["drives"][0][k] for k in WHEEL_KEYS}
    bus = {"name": "can0", "interface": "socketcand", "channel": "can0", "kwargs": {"host": "127.0.0.1", "port": 29536},
           "sync_period_ms": 1000.0 / hz, "bitrate": bitrate}
    return yaml.safe_dump({"buses": [bus],
                           "drives": [{"name": f"j{i}", "namespace": "limit", "node_id": i, "bus": "can0", **wheel}
                                      for i in range(1, drives + 1)]}, sort_keys=False)


#: The second run: config/rover.yaml's six wheels on their two buses (SYNC every 10 ms, commanded
#: at 100 Hz) beside a six-joint arm on a third bus, ``can2``, at 500 Hz (the arm's joints with the
#: wheels' settings: this module's six drives, moved to can2)
ARM_BUS = "can2"


def twelve_config_text() -> str:
    """Twelve drives on three buses: the rover's wheels as shipped, and the six-drive config's bus and drives as ``can2``."""
    rover = yaml.safe_load((REPO / "config" / "rover.yaml").read_text())
    arm = yaml.safe_load(config_text())
    arm["buses"][0].update(name=ARM_BUS, channel=ARM_BUS)
    for d in arm["drives"]:
        d.update(bus=ARM_BUS, namespace="arm")
    return yaml.safe_dump({**rover, "buses": rover["buses"] + arm["buses"], "drives": rover["drives"] + arm["drives"]},
                          sort_keys=False)


@contextmanager
def limit_config(drives: int = DRIVES, hz: float = HZ, text: str | None = None) -> Iterator[Path]:
    """The generated config (``text``, by default :func:`config_text`) in a temporary directory
    under benchmarks/out/ (ignored by git): the stack run names its config relative to the repository."""
    out = REPO / "benchmarks" / "out"
    out.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        path = Path(tmp) / (f"limit_{drives}x{hz:g}hz.yaml" if text is None else "limit_12_three_buses.yaml")
        path.write_text(text if text is not None else config_text(drives, hz))
        yield path


def traffic(frames: list[tuple[float, int, bytes]]) -> dict[str, float]:
    """Frames/s and bus load (over 1 Mbit/s, without and with worst-case stuffing) of the frames
    a listener saw while every drive was commanded: between the 2nd and the 98th percentile of the
    set-point RPDOs' stamps (a few set-points go out at enable, before the commands; none after
    them, while the run still reads its figures)."""
    rpdos = sorted(t for t, cob, _ in frames if 0x301 <= cob <= 0x37F)
    if len(rpdos) < 10 or not any(is_tpdo(cob) for _, cob, _ in frames):
        return {}
    start, end = rpdos[len(rpdos) // 50], rpdos[len(rpdos) * 49 // 50]
    window = [(cob, data) for t, cob, data in frames if start <= t <= end]
    span = max(end - start, 1e-9)
    # what the emulator itself puts on the bus: the SYNC (its timer) and the drive models' TPDOs
    emulated = sum(1 for cob, _ in window if cob == 0x080 or is_tpdo(cob))
    nominal = sum(frame_bits(len(d), worst_case_stuffing=False) for _, d in window)
    worst = sum(frame_bits(len(d)) for _, d in window)
    return {"frames_per_s": len(window) / span, "emulator_frames_per_s": emulated / span,
            "load": nominal / span / WIRE_BITRATE,
            "load_worst_case": worst / span / WIRE_BITRATE}


def stack(config: Path, seconds: float, hz: float = HZ, prefix: str = "bus_limit_", channel: str = "can0",
          joint_commands: bool = False) -> dict[str, Any]:
    """The stack run on ``config`` commanded at ``hz`` (0: each drive at its bus's SYNC rate), keys
    prefixed, with the traffic the listener of ``channel`` saw; ``joint_commands``: the set-points
    as one /joint_commands message a tick (stack_run.run_stack)."""
    seen: list[list[tuple[float, int, bytes]]] = []

    class Recording(stack_run.Listener):
        def close(self) -> None:
            super().close()
            if self.channel == channel:
                seen.append(self.frames)

    listener = stack_run.Listener
    stack_run.Listener = Recording  # type: ignore[misc]  # the run's own listener, its frames kept
    try:
        out = stack_run.run_stack(config, seconds, hz, ("--drive-processes",), joint_commands)
    finally:
        stack_run.Listener = listener  # type: ignore[misc]
    carried = traffic(seen[0]) if seen else {}
    if prefix:
        out.pop("config", None)
    figures = {f"{prefix}{k}": v for k, v in out.items()}
    figures.update({f"{prefix}hz": hz, f"{prefix}frames_per_s": round(carried.get("frames_per_s", 0.0)),
                    f"{prefix}emulator_frames_per_s": round(carried.get("emulator_frames_per_s", 0.0)),
                    f"{prefix}bus_load": round(carried.get("load", 0.0), 3),
                    f"{prefix}bus_load_worst_case_stuffing": round(carried.get("load_worst_case", 0.0), 3)})
    return figures


#: The least share of the frames the emulator owes (its SYNC, the drive models' TPDOs) the listener
#: must have seen for the stack's figures to count: below, the emulator (or the listener, a client
#: like the drives) did not carry the load, and command latency, SYNC error and TPDO loss measure
#: the machine, not the stack. The driver's set-points are not counted: a driver that sent too few
#: must be MISSED, not excused.
CARRIED_MIN = 0.9


#: A run that put fewer of its commands on the wire measured less work than it claims. A streamed
#: joint refuses a set-point more than two SYNC periods at max velocity from the last it sent, so
#: after a stall (28 commands at 500 Hz) the stack run's ramp is planned again from where the joint
#: stands (stack_run.Ramps); the refusals until then count here. Quiet, 0.2 % are lost (a command
#: replaced by the joint's next before it was taken).
SETPOINT_LOSS_MAX = 0.05


def not_carried(figures: dict[str, Any], drives: int = DRIVES, hz: float = HZ, prefix: str = "bus_limit_") -> str | None:
    """Why the stack run's figures do not count (the emulator did not carry the load, or a drive
    faulted or stopped itself: its EMCY), or None.
    ``drives``: on the bus whose listener the figures came from."""
    due = (1 + 2 * drives) * hz  # its SYNC and two TPDOs per drive every cycle
    seen = figures.get(f"{prefix}emulator_frames_per_s", 0)
    if seen < CARRIED_MIN * due:
        return f"the listener saw {seen} of the {due:.0f} SYNC and TPDO frames/s the emulator owes ({seen / due:.0%})"
    emcy = figures.get(f"{prefix}emcy_in_window")
    if emcy:
        return f"drives faulted or stopped themselves during the run ({', '.join(emcy)})"
    loss = figures.get(f"{prefix}tpdo_loss") or 0
    if loss < 0:
        return f"the listener missed {-loss} TPDOs the driver applied"
    setpoints = figures.get(f"{prefix}setpoint_loss_fraction") or 0.0
    if setpoints > SETPOINT_LOSS_MAX:
        refused = figures.get(f"{prefix}commands_refused") or 0
        why = (f"the driver refused {refused} of them, the last: {figures.get(f'{prefix}last_refusal')}" if refused else
               "none refused by the driver: lost before it (the publisher or DDS) or replaced in the handoff")
        return f"{setpoints:.0%} of the commands never went on the wire as a set-point ({why})"
    return None


def every_stop(runs: list[dict[str, Any]], prefix: str = "bus_limit_") -> dict[str, Any]:
    """The drives' stops (EMCYs in the window) of every attempt (by its try where stack_run.two_tries
    says it, else its place): a run tried again because its drives faulted must not lose the fault when
    the next one is clean."""
    stops = [f"run {run.get(f'{prefix}run_try', n)}: {stop}" for n, run in enumerate(runs, start=1)
             for stop in run.get(f"{prefix}emcy_in_window") or []]
    return {f"{prefix}emcy_in_window": stops, f"{prefix}drive_stops": len(stops)}


def ratio(figures: dict[str, Any], base: dict[str, Any], prefix: str = "bus_limit_") -> dict[str, Any]:
    """The canopen same work's figures (prefixed) and the CPU ratio, where both were measured."""
    out = {f"{prefix}{k}": v for k, v in base.items()}
    cpu, base_cpu = figures.get(f"{prefix}cpu_core_fraction"), base.get("baseline_canopen_same_work_rt_cpu_core_fraction")
    if cpu and base_cpu:
        out[f"{prefix}cpu_ratio_canopen"] = round(cpu / base_cpu, 2)
    return out


def measured(text: str | None, seconds: float, hz: float, prefix: str, channel: str, priority: int) -> dict[str, Any]:
    """One run: the stack on the generated config (``text``; None: the six drives), whether the
    emulator carried ``channel``'s load (its six drives at 500 Hz), and the canopen same work."""
    import same_work
    from verdicts import InvalidBaseline

    with limit_config(text=text) as config:
        figures = stack(config, seconds, hz, prefix, channel)
        figures[f"{prefix}not_carried"] = not_carried(figures, prefix=prefix)
        try:
            base = same_work.baseline_same_work(config, seconds, hz, priority)
        except InvalidBaseline as err:
            base = {}
            figures[f"{prefix}baseline_invalid"] = str(err)
    figures.update(ratio(figures, base, prefix))
    return figures


def main() -> int:
    """``bus_limit.py [SECONDS] [--six | --twelve]``: both runs by default."""
    from nodes.process.params import PARAMS

    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    seconds = float(args[0]) if args else 15.0
    priority = int(PARAMS["realtime_priority"].default)  # type: ignore[call-overload]
    figures: dict[str, Any] = {"harness_nice": stack_run.harness_ahead(), "harness_fifo_priority": stack_run.harness_priority()}
    if "--twelve" not in sys.argv:
        figures.update(measured(None, seconds, HZ, "bus_limit_", "can0", priority))
    if "--six" not in sys.argv:  # each drive commanded at its bus's SYNC rate: wheels 100 Hz, the arm 500 Hz
        figures.update(measured(twelve_config_text(), seconds, 0.0, "bus_limit_12_", ARM_BUS, priority))
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Bench commands that move a drive through the driver (limits enforced): enable/disable/
fault-reset/home, move, jog, step-test.

Owner: the CLI's main thread; the driver it starts owns its own threads.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from can_config.errors import CommandRejected, ConfigError
from can_config.objects import SUPPORTED_MODE_BIT, OperationMode
from motor_driver.follow.trajectory import trapezoid
from motor_driver.protocol.units import shortest_delta_deg
from rovercan.argtypes import real
from rovercan.bench.common import (
    CliError,
    add_bus_args,
    add_drive_args,
    add_json,
    add_master_flags,
    bench_driver,
    emit,
    output_file,
)

if TYPE_CHECKING:
    from motor_driver.drive import Drive, DriveState

logger = logging.getLogger(__name__)


def cmd_drive(args: argparse.Namespace) -> int:
    with bench_driver(args, args.node) as drive:
        node_id = drive.node_id
        if args.action == "fault-reset":
            drive.recover()
        elif args.action == "disable":
            drive.disable()
        elif args.action == "enable":
            drive.enable()
            if args.hold:
                time.sleep(args.hold)
        elif args.action == "home":
            drive.enable()
            drive.home()
        state = drive.snapshot()
        result: dict[str, Any] = {"node": node_id, "action": args.action, "state": state.state.name,
                                  "angle_deg": round(state.angle_deg, 3)}
        if args.action == "enable":  # the bench never leaves a drive armed behind it
            result["on_exit"] = (f"held enabled {args.hold:g} s, then disabled" if args.hold else
                                 "disabled again as the command exits; --hold S keeps it enabled S seconds first")
        emit(args, result, f"node {node_id}")
    return 0


class UnitCheck:
    """While a drive moves: does the distance its position covered match what its reported
    velocity adds up to? Position counts and velocity units come from different objects (0x608F,
    0x60A9, gear ratio); a wrong ``counts_per_rev`` shows as a ratio far from 1."""

    TOLERANCE = 0.2
    MIN_TRAVEL_DEG = 2.0

    def __init__(self, drive: Drive) -> None:
        self.drive = drive
        self.samples: list[tuple[float, float, float]] = []

    def sample(self) -> None:
        s = self.drive.snapshot()
        self.samples.append((time.monotonic(), s.angle_deg, s.velocity_deg_s))

    def verdict(self) -> str | None:
        moved = reported = 0.0
        for (t0, a0, v0), (t1, a1, v1) in itertools.pairwise(self.samples):
            step = a1 - a0
            if self.drive.config.is_continuous:
                step = shortest_delta_deg(step)  # across the wrap of a continuous joint
            moved += step
            reported += (v0 + v1) / 2 * (t1 - t0)
        if max(abs(moved), abs(reported)) < self.MIN_TRAVEL_DEG:
            return None  # too little motion to judge
        if reported and abs(moved / reported - 1) <= self.TOLERANCE:
            return None
        ratio = f"x{moved / reported:.2f}" if reported else "no velocity reported"
        return (f"node {self.drive.node_id}: the position moved {moved:.1f} deg while the reported velocity adds"
                f" up to {reported:.1f} deg ({ratio}): counts_per_rev looks wrong (or gear_ratio, or the"
                " drive's velocity unit 0x60A9); positions and velocities disagree")

    def warn(self) -> None:
        text = self.verdict()
        if text is not None:
            print(f"rovercan: warning: {text}", file=sys.stderr, flush=True)


def has_profile_position(drive: Drive) -> bool:
    return bool(drive.power.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_POSITION] & 1)


def command_angle(drive: Drive, angle_deg: float) -> float:
    """The angle to command for a multi-turn ``angle_deg``: a continuous joint takes an angle
    modulo 360 (and moves the short way to it), so after a few turns a measured start plus a step
    is brought back into -360..360 first."""
    return math.fmod(angle_deg, 360.0) if drive.config.is_continuous else angle_deg


def stream_to(drive: Drive, target_deg: float, speed_deg_s: float | None = None,
              on_tick: Callable[[], None] | None = None) -> float:
    """A move on a drive whose only position modes are cyclic or interpolated (the SCHUNK PRL120):
    a trapezoid of set-points (:func:`motor_driver.follow.trajectory.trapezoid`), one per SYNC period,
    through the driver's streaming path (limits enforced there), then waits until the joint is
    within 0.2 deg. Returns the target."""
    cfg = drive.config
    drive.motion.check_position(command_angle(drive, target_deg))  # beyond a limit: refused before anything is sent
    period = drive.cache.sync_period_s
    speed = min(speed_deg_s or cfg.profile_velocity_deg_s, cfg.max_velocity_deg_s)
    for position in trapezoid(drive.snapshot().angle_deg, target_deg, speed, cfg.profile_acceleration_deg_s2, period):
        drive.stream_position(command_angle(drive, position))
        if on_tick is not None:
            on_tick()
        time.sleep(period)
    if on_tick is not None:
        return target_deg  # the caller keeps sampling
    deadline = time.monotonic() + 3.0
    while abs(drive.snapshot().angle_deg - target_deg) > 0.2:
        if time.monotonic() > deadline:
            raise CliError(f"node {drive.node_id}: at {drive.snapshot().angle_deg:.2f} deg, not at {target_deg:g} deg"
                           " 3 s after the streamed move ended")
        time.sleep(period)
    return target_deg


def cmd_move(args: argparse.Namespace) -> int:
    with bench_driver(args, args.node) as drive:
        node_id = drive.node_id
        if args.speed is not None and not 0 < args.speed <= drive.config.max_velocity_deg_s:
            raise ConfigError(f"--speed {args.speed:g} deg/s: allowed 0 < speed <= {drive.config.max_velocity_deg_s:g}"
                              " (max_velocity_deg_s)")
        drive.enable()
        if has_profile_position(drive):
            if args.speed is not None:
                drive.motion.set_profile_velocity(args.speed)
            check = UnitCheck(drive)
            target = drive.move_to(args.degrees)
            sampling = threading.Event()

            def sample_until_done() -> None:
                while not sampling.wait(0.01):
                    check.sample()

            sampler = threading.Thread(target=sample_until_done, daemon=True, name="rovercan-unit-check")
            sampler.start()
            try:
                drive.wait_target_reached(args.wait)
            finally:
                sampling.set()
                sampler.join()
            check.warn()
        else:  # cyclic or interpolated position only: streamed set-points
            target = stream_to(drive, args.degrees, args.speed)
        drive.disable()  # the bench never leaves a drive armed: what is said is the state it is left in
        state = drive.snapshot()
        emit(args, {"node": node_id, "target_deg": round(target, 3), "angle_deg": round(state.angle_deg, 3),
                    "state": state.state.name, "verdict": state.verdict.cause}, f"node {node_id} moved")
    return 0


def has_profile_velocity(drive: Drive) -> bool:
    return bool(drive.power.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_VELOCITY] & 1)


def stream_jog(drive: Drive, velocity: float, seconds: float) -> DriveState:
    """A jog on a drive without profile velocity: streamed positions, ramped at the profile
    acceleration up to ``velocity``, held for ``seconds``, ramped down. Returns the state seen at
    the end of the hold."""
    cfg = drive.config
    period = drive.cache.sync_period_s
    dv = cfg.profile_acceleration_deg_s2 * period
    position = drive.snapshot().angle_deg
    v = 0.0
    end = time.monotonic() + seconds
    peak = None
    while peak is None or abs(v) > 1e-9:
        goal = velocity if time.monotonic() < end else 0.0
        if goal == 0.0 and peak is None:
            peak = drive.snapshot()
        v += max(-dv, min(dv, goal - v))
        position += v * period
        drive.stream_position(position)
        time.sleep(period)
    return peak


def cmd_jog(args: argparse.Namespace) -> int:
    with bench_driver(args, args.node) as drive:
        node_id = drive.node_id
        drive.enable()
        if not has_profile_velocity(drive):  # a position-only drive: a streamed ramp
            peak = stream_jog(drive, args.velocity, args.seconds)
        else:
            end = time.monotonic() + args.seconds
            sent = 0
            check = UnitCheck(drive)
            while time.monotonic() < end:
                try:
                    drive.set_velocity(args.velocity)
                except CommandRejected as err:
                    if sent:  # refused on the way (a limit ahead): the drive had moved, so exit 1, not 2
                        raise CliError(str(err)) from err
                    raise
                sent += 1
                check.sample()
                time.sleep(0.05)
            peak = drive.snapshot()
            drive.set_velocity(0.0)
            check.warn()
        emit(args, {"node": node_id, "velocity_deg_s": round(peak.velocity_deg_s, 3),
                    "angle_deg": round(peak.angle_deg, 3)}, f"node {node_id} jogged")
    return 0


# ------------------------------------------------------------------------------ step test
#: Stale-data periods the step test waits for a fresh position before it starts.
FRESH_START_SYNCS = 50


def fresh_angle(drive: Drive) -> float:
    """The joint angle from fresh data: a stale snapshot's angle is NaN (a start from it would
    leave every metric NaN). Waits up to FRESH_START_SYNCS SYNC periods (1 s at least)."""
    bound_s = max(1.0, FRESH_START_SYNCS * drive.cache.sync_period_s)
    seen = [drive.snapshot()]

    def measured() -> bool:  # the driver's verdict, read once per look: the angle returned is the one judged
        seen[0] = drive.snapshot()
        return seen[0].verdict.fresh

    if not drive.cache.wait_until(measured, bound_s):
        raise CliError(f"node {drive.node_id}: no fresh position from the drive within {bound_s:g} s after enabling"
                       f" it ({seen[0].verdict.text()}): nothing was moved; check the bus and the drive's TPDOs,"
                       " then run the step test again")
    return seen[0].angle_deg


def step_metrics(t: list[float], y: list[float], start: float, step: float, torque: list[float]) -> dict[str, float]:
    """Rise time (10-90 %), overshoot (%), settling time (2 % band), steady-state error, peak torque."""
    final = start + step
    sign = 1.0 if step >= 0 else -1.0
    rel = [(v - start) * sign / abs(step) for v in y]
    t10 = next((ti for ti, r in zip(t, rel, strict=True) if r >= 0.1), math.nan)
    t90 = next((ti for ti, r in zip(t, rel, strict=True) if r >= 0.9), math.nan)
    overshoot = max(0.0, (max(rel) - 1.0) * 100.0)
    band = 0.02
    settle = 0.0
    for ti, r in zip(t, rel, strict=True):
        if abs(r - 1.0) > band:
            settle = ti
    return {"rise_time_s": round(t90 - t10, 4), "overshoot_pct": round(overshoot, 3),
            "settling_time_s": round(settle, 4), "steady_state_error_deg": round(abs(final - y[-1]), 4),
            "peak_torque_nm": round(max((abs(x) for x in torque if not math.isnan(x)), default=math.nan), 4)}


def _plot_step(png: Path, node_id: int, step: float, metrics: dict[str, Any], ts: list[float],
               series: tuple[list[float], list[float], list[float], list[float]]) -> None:
    """The step test's PNG: set-point and angle, velocity, torque over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    setpoint, angle, velocity, torque = series
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    axes[0].plot(ts, setpoint, "--", label="setpoint")
    axes[0].plot(ts, angle, label="angle")
    axes[0].set_ylabel("deg")
    axes[0].legend()
    axes[0].set_title(f"step test node {node_id}: {step:g} deg, rise {metrics['rise_time_s']} s,"
                      f" overshoot {metrics['overshoot_pct']} %")
    axes[1].plot(ts, velocity)
    axes[1].set_ylabel("deg/s")
    axes[2].plot(ts, torque)
    axes[2].set_ylabel("Nm")
    axes[2].set_xlabel("s")
    for ax in axes:
        ax.grid(True)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def cmd_step_test(args: argparse.Namespace) -> int:
    out = Path(args.out)
    for suffix in (".png", ".json"):  # before the motor moves: a measurement is not lost to its path
        output_file(out.with_suffix(suffix), "--out")
    with bench_driver(args, args.node) as drive:
        node_id = drive.node_id
        if drive.config.is_continuous and abs(args.step) >= 180:
            raise ConfigError(f"--step {args.step:g}: a continuous joint moves the short way, so a step test"
                              " needs |step| < 180 deg")
        drive.enable()
        start = fresh_angle(drive)
        t0 = time.monotonic()
        ts: list[float] = []
        setpoint: list[float] = []
        angle: list[float] = []
        velocity: list[float] = []
        torque: list[float] = []
        target = start + args.step

        def sample() -> None:
            s = drive.snapshot()
            ts.append(time.monotonic() - t0)
            setpoint.append(target)
            angle.append(s.angle_deg)
            velocity.append(s.velocity_deg_s)
            torque.append(s.torque_nm)

        if has_profile_position(drive):
            target = drive.move_to(command_angle(drive, target))
        else:  # position streamed: the set-point is a trapezoid, sampled as it goes
            stream_to(drive, target, on_tick=sample)
        while time.monotonic() - t0 < args.seconds:
            sample()
            time.sleep(0.005)
    metrics = step_metrics(ts, angle, start, args.step, torque)
    metrics.update({"step_deg": args.step, "start_deg": round(start, 3),
                    "profile_velocity_deg_s": drive.config.profile_velocity_deg_s,
                    "profile_acceleration_deg_s2": drive.config.profile_acceleration_deg_s2})
    _plot_step(out.with_suffix(".png"), node_id, args.step, metrics, ts, (setpoint, angle, velocity, torque))
    out.with_suffix(".json").write_text(json.dumps(metrics, indent=2) + "\n")
    emit(args, metrics, f"step test node {node_id} -> {out.with_suffix('.png')}")
    return 0


def _drive_command_args(parser: argparse.ArgumentParser) -> None:
    """What every command that drives a motor takes: the drive, the bus, the master checks, --json."""
    add_drive_args(parser)
    add_bus_args(parser)
    add_master_flags(parser)
    add_json(parser)


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """The motion commands' parsers."""
    for action, text in (("enable", "boot and enable a drive (disabled again on exit)"),
                         ("disable", "boot and disable a drive"), ("fault-reset", "reset a drive's fault"),
                         ("home", "home a drive with its configured method")):
        p = sub.add_parser(action, help=text)
        p.add_argument("node")
        if action == "enable":
            p.add_argument("--hold", type=real(0, 86400), default=0.0, help="stay enabled for S seconds")
        _drive_command_args(p)
        p.set_defaults(func=cmd_drive, action=action)

    p = sub.add_parser("move", help="move a drive to an angle and wait for target reached")
    p.add_argument("node")
    p.add_argument("degrees", type=real(-1e6, 1e6), help="joint angle (limits: the config's)")
    p.add_argument("--speed", type=real(0.001, 1e6), help="profile velocity, deg/s")
    p.add_argument("--wait", type=real(0.1, 3600), default=None, metavar="S",
                   help="seconds to wait for target reached (default: 2 s + the move's own time at its profile)")
    _drive_command_args(p)
    p.set_defaults(func=cmd_move)

    p = sub.add_parser("jog", help="run a drive at a velocity for a time")
    p.add_argument("node")
    p.add_argument("velocity", type=real(-1e6, 1e6), help="deg/s")
    p.add_argument("--for", dest="seconds", type=real(0.01, 3600), required=True, help="seconds")
    _drive_command_args(p)
    p.set_defaults(func=cmd_jog)

    p = sub.add_parser("step-test", help="position step: PNG plot and JSON metrics")
    p.add_argument("node")
    p.add_argument("--step", type=real(-3600, 3600, nonzero=True), required=True, help="step in degrees")
    p.add_argument("--seconds", type=real(0.1, 600), default=3.0, help="recording length")
    p.add_argument("--out", default="step_test", help="output path without suffix (.png and .json)")
    _drive_command_args(p)
    p.set_defaults(func=cmd_step_test)

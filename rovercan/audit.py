"""``rovercan audit``: what the benchmarks measure, measured on the bus the drives are on.

On the rover's own CAN (the Orin's can0, a PCAN adapter) or the simulator, with the rover's
driver stopped: the audit boots the configured drives of one bus with the driver, arms them
and commands zero velocity (the wheels stay still but powered: chock the rover; or
``--no-motion``), and a second connection to the same bus (a listener) records every frame
with its bus timestamp. From those frames:

* SYNC period error (p50 / p99 / max) against ``sync_period_ms``;
* command -> RPDO latency: from the driver's call to the RPDO on the wire, for its own commands;
* TPDO loss and late TPDOs per drive: SYNC-driven TPDOs expected from the SYNCs seen, and
  those that came later than half a SYNC period after their SYNC;
* SDO round trip per node (expedited upload of 0x1000);
* heartbeat period error per node, against a quarter of its ``heartbeat_period_ms``;
* bus load (worst-case stuffing) and error frames, beside the planned load (``rovercan plan``).

Each figure is compared with its target; exit 1 names every target missed.

Owner: the CLI's main thread.
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can

from can_config import RoverConfig, load_config
from can_config.bits import frame_bits
from can_config.errors import ConfigError, MotorError
from rovercan.argtypes import real
from rovercan.bench.common import CliError, add_bus_args, add_json, emit, open_bus

if TYPE_CHECKING:
    from motor_driver.bus.link import KernelBusHealth

#: Targets (the README's Performance section; SYNC error is the acceptance bound, 200 us the aim).
TARGETS = {"sync_error_p99_us": 500.0, "cmd_latency_p99_ms": 2.0, "tpdo_loss": 0, "late_tpdo_fraction": 0.01,
           "sdo_rtt_p99_ms": 5.0, "bus_load_pct": 50.0, "error_frames": 0}
#: A drive's heartbeat may be off its period by at most this fraction (p99): more eats into the
#: margin between the period and the consumer time the driver uses to declare it lost.
HEARTBEAT_ERROR_FRACTION = 0.25
SDO_SAMPLES = 20
COMMAND_PERIOD_S = 0.01


@dataclass
class Figure:
    name: str
    value: float | int | None
    target: str
    ok: bool

    def row(self) -> dict[str, Any]:
        value = round(self.value, 4) if isinstance(self.value, float) else self.value
        return {"figure": self.name, "measured": value, "target": self.target, "status": "ok" if self.ok else "MISSED"}


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * (len(ordered) - 1)))]


class Recorder(threading.Thread):
    """Every frame of the listener connection with its bus timestamp."""

    def __init__(self, bus: can.BusABC) -> None:
        super().__init__(daemon=True, name="rovercan-audit-listener")
        self.bus = bus
        self.frames: list[can.Message] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append(msg)


def one_bus(config: RoverConfig, name: str | None) -> RoverConfig:
    bus = config.bus(name) if name else config.buses[0]
    drives = tuple(d for d in config.drives if d.bus == bus.name)
    if not drives:
        raise ConfigError(f"audit: no drive on bus {bus.name!r}; pick one with --bus")
    return RoverConfig((bus,), drives, None, config.source)


def exercise(config: RoverConfig, seconds: float,
             motion: bool) -> tuple[dict[int, list[float]], dict[int, list[float]], float]:
    """Boot the drives, command zero velocity every COMMAND_PERIOD_S (when ``motion``) and time
    SDO round trips. Returns (command send times by node, SDO round trips in ms by node, when
    the drives were booted: from then on their heartbeat runs at the configured period)."""
    from motor_driver import MotorDriver

    sent: dict[int, list[float]] = {d.node_id: [] for d in config.drives}
    rtts: dict[int, list[float]] = {d.node_id: [] for d in config.drives}
    with MotorDriver(config, force=True).start() as driver:
        booted = time.time()
        if motion:
            for drive in driver:
                drive.enable()
                drive.set_velocity(0.0)  # the mode switch happens here, outside the measured window
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for drive in driver:
                if motion:
                    t = time.time()
                    drive.set_velocity(0.0)
                    sent[drive.node_id].append(t)
            time.sleep(COMMAND_PERIOD_S)
        for drive in driver:
            for _ in range(SDO_SAMPLES):
                start = time.perf_counter()
                drive.sdo_read(0x1000, 0)
                rtts[drive.node_id].append((time.perf_counter() - start) * 1000)
    return sent, rtts, booted


def analyse(config: RoverConfig, frames: list[can.Message], sent: dict[int, list[float]],
            rtts: dict[int, list[float]], window: tuple[float, float], booted: float | None = None) -> list[Figure]:
    from can_config import load_drive_od
    from motor_driver.bus.load import plan_load
    from motor_driver.protocol.pdo import plan_pdos

    bus_cfg = config.buses[0]
    t0, t1 = window
    inside = [m for m in frames if t0 <= m.timestamp <= t1]
    figures: list[Figure] = []
    syncs = [m.timestamp for m in inside if m.arbitration_id == 0x080 and not m.is_error_frame]
    errors_us = [abs((b - a) - bus_cfg.sync_period_s) * 1e6 for a, b in itertools.pairwise(syncs)]
    if errors_us:
        figures += [Figure("SYNC period error p50, us", statistics.median(errors_us), "", True),
                    Figure("SYNC period error p99, us", pct(errors_us, 0.99),
                           f"<= {TARGETS['sync_error_p99_us']:g}", pct(errors_us, 0.99) <= TARGETS["sync_error_p99_us"]),
                    Figure("SYNC period error max, us", max(errors_us), "", True)]
    else:
        figures.append(Figure("SYNC frames seen", 0, "> 0", False))
    for drive in config.drives:
        plan = plan_pdos(load_drive_od(drive.eds, drive.node_id), drive.node_id)
        node = drive.node_id
        # command -> RPDO: the n-th velocity RPDO on the wire answers the n-th call
        rpdo = plan.rpdo_with(0x60FF)
        if sent[node] and rpdo is not None:
            figures += _latency_figures(node, [m.timestamp for m in frames if m.arbitration_id == rpdo.cob_id], sent[node])
        figures += _tpdo_figures(node, plan.tpdos, inside, syncs, bus_cfg.sync_period_s)
        if rtts[node]:
            p99 = pct(rtts[node], 0.99)
            figures.append(Figure(f"node {node}: SDO round trip p99, ms", p99, f"<= {TARGETS['sdo_rtt_p99_ms']:g}",
                                  p99 <= TARGETS["sdo_rtt_p99_ms"]))
        # once booted (the NMT reset restarts the heartbeat and boot writes its period), and
        # without the boot-up message, which is no heartbeat of the period
        beats = [m.timestamp for m in inside if m.arbitration_id == 0x700 + node and m.data and m.data[0]
                 and m.timestamp >= (booted or t0)]
        hb_errors = [abs((b - a) - drive.heartbeat_period_s) * 1000 for a, b in itertools.pairwise(beats)]
        if hb_errors:
            p99 = pct(hb_errors, 0.99)
            bound = HEARTBEAT_ERROR_FRACTION * drive.heartbeat_period_s * 1000
            figures.append(Figure(f"node {node}: heartbeat period error p99, ms", p99, f"<= {bound:g}", p99 <= bound))
        else:
            figures.append(Figure(f"node {node}: heartbeats seen", 0, "> 0", False))
    span = max(t1 - t0, 1e-9)
    bits = sum(frame_bits(min(m.dlc, 8), extended=m.is_extended_id) for m in inside if not m.is_error_frame)
    load = bits / (span * bus_cfg.bitrate)
    planned = next(p.load for p in plan_load(config) if p.bus == bus_cfg.name)
    error_frames = sum(1 for m in inside if m.is_error_frame)
    # in percent of the bitrate, as `rovercan plan` says it
    figures += [Figure("bus load (measured, worst-case stuffing), %", 100 * load, f"<= {TARGETS['bus_load_pct']:g}",
                       100 * load <= TARGETS["bus_load_pct"]),
                Figure("bus load (planned, rovercan plan), %", 100 * planned, "<= 100 (refused above)", planned <= 1.0),
                Figure("error frames", error_frames, "0", error_frames <= TARGETS["error_frames"])]
    return figures


def _latency_figures(node: int, on_wire: list[float], sent: list[float]) -> list[Figure]:
    """Command -> RPDO: each call's frame is the first on the wire at or after it."""
    latencies = []
    j = 0
    for t_sent in sent:
        while j < len(on_wire) and on_wire[j] < t_sent:
            j += 1
        if j == len(on_wire):
            break
        latencies.append((on_wire[j] - t_sent) * 1000)
        j += 1
    if not latencies:
        return []
    p99 = pct(latencies, 0.99)
    return [Figure(f"node {node}: command -> RPDO p50, ms", statistics.median(latencies), "", True),
            Figure(f"node {node}: command -> RPDO p99, ms", p99, f"<= {TARGETS['cmd_latency_p99_ms']:g}",
                   p99 <= TARGETS["cmd_latency_p99_ms"])]


def _tpdo_figures(node: int, tpdos: Any, inside: list[can.Message], syncs: list[float], period_s: float) -> list[Figure]:
    """SYNC-driven TPDOs: expected from the SYNCs seen, late when more than half a period after theirs."""
    figures: list[Figure] = []
    for pdo in tpdos:
        if not 1 <= pdo.trans_type <= 240 or len(syncs) < 3:
            continue
        got = [m.timestamp for m in inside if m.arbitration_id == pdo.cob_id]
        expected = (len(syncs) - 1) // pdo.trans_type
        received = sum(1 for t in got if syncs[0] < t <= syncs[-1])
        lost = max(0, expected - received)
        late = 0
        for t in got:
            before = [s for s in syncs if s <= t]
            if before and t - before[-1] > period_s / 2:
                late += 1
        late_fraction = late / max(1, len(got))
        figures += [Figure(f"node {node}: TPDO 0x{pdo.cob_id:03X} lost", lost, "0", lost <= TARGETS["tpdo_loss"]),
                    Figure(f"node {node}: TPDO 0x{pdo.cob_id:03X} late fraction", late_fraction,
                           f"<= {TARGETS['late_tpdo_fraction']:g}", late_fraction <= TARGETS["late_tpdo_fraction"])]
    return figures


def kernel_health(config: RoverConfig) -> KernelBusHealth | None:
    """The audited bus as its kernel knows it (a socketcan bus), else None."""
    from motor_driver.bus.link import read_kernel_health

    bus = config.buses[0]
    return read_kernel_health(bus.channel) if bus.interface == "socketcan" else None


def kernel_figures(before: KernelBusHealth | None, after: KernelBusHealth | None, seconds: float) -> list[Figure]:
    """The controller's state after the run (ERROR-ACTIVE, or a vcan's none) and the error and drop
    counters that rose during it (motor_driver.bus.link.rising: each with what to do)."""
    from motor_driver.bus.link import rising

    if before is None or after is None:
        return []
    problems = after.problems() + rising(before, after, seconds)
    return [Figure(f"{after.interface}: controller state {after.state or 'none (' + after.kind + ')'}",
                   after.tx_errors, "ERROR-ACTIVE (or no controller)", after.ok),
            Figure(f"{after.interface}: counters risen during the audit" + (f" ({'; '.join(problems)})"
                                                                            if problems else ""),
                   len(problems), "0", not problems)]


def cmd_audit(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.seconds) and 0.5 <= args.seconds <= 600):
        raise ConfigError(f"--seconds {args.seconds}: allowed 0.5 to 600")
    config = one_bus(load_config(args.config), args.bus)
    kernel_before = kernel_health(config)
    listener = open_bus(args)
    recorder = Recorder(listener)
    recorder.start()
    try:
        time.sleep(0.1)  # the listener is live
        start = time.time()
        try:
            sent, rtts, booted = exercise(config, args.seconds, not args.no_motion)
        except MotorError as err:
            raise CliError(f"audit: the drives could not be exercised: {err}") from err
        window = (start, time.time())
        time.sleep(0.1)
    finally:
        recorder.stop.set()
        recorder.join(2.0)
        listener.shutdown()
    figures = analyse(config, recorder.frames, sent, rtts, window, booted)
    figures += kernel_figures(kernel_before, kernel_health(config), window[1] - window[0])
    emit(args, [f.row() for f in figures], f"audit of bus {config.buses[0].name} ({args.seconds:g} s)",
         ["figure", "measured", "target", "status"])
    missed = [f.name for f in figures if not f.ok]
    if missed:
        print(f"rovercan audit: targets missed: {'; '.join(missed)}", file=sys.stderr)
        return 1
    return 0



def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """The audit commands' parsers."""
    p = sub.add_parser("audit", help="measure SYNC, command latency, TPDO loss, SDO, heartbeats and load on the bus")
    p.add_argument("--config", required=True, help="the rover config (its drives on the audited bus are exercised)")
    p.add_argument("--bus", help="which bus of the config (default: the first)")
    p.add_argument("--seconds", type=real(0.5, 600), default=5.0, help="how long to measure (0.5 to 600)")
    p.add_argument("--no-motion", action="store_true", help="do not arm the drives (no command latency figure)")
    add_bus_args(p)
    add_json(p)
    p.set_defaults(func=cmd_audit)

"""The scaling curve (issue 55): the stack run (driver + ROS node, stack_run.run_stack) on 1, 3, 6,
12 and 18 drives on one bus at 100, 250 and 500 Hz CSP, each a short run; the figure is the
measured process's CPU per drive-cycle (CPU seconds / (drives x command rate x seconds), in us),
with command p99 and SYNC error p99. Linear growth keeps it constant: ``scaling_cost_spread`` is
the largest over the smallest, minus 1, over the runs the emulator carried (bus_limit.not_carried).
That figure also divides the process's fixed cost (executors, supervisor, DDS: paid with one drive
as with eighteen) and its cost per SYNC cycle among the drive-cycles, so it is large for any
process with a fixed cost. What each added drive costs, (CPU(N) - CPU(1)) / ((N - 1) x rate) at
one rate, has both taken out: ``scaling_added_cost_spread`` is its largest spread within one rate
(from 1 to N drives: growth in drives, the curve's question), and a knee (a cost per drive that
grows with the load) shows there. Across rates it differs by what a drive costs per second
whatever the rate (its state published at a rate of its own): ``scaling_added_cost_by_rate``.

A combination whose traffic (a SYNC, a set-point RPDO and two TPDOs per drive every cycle, no bit
stuffing) exceeds one 1 Mbit/s bus is dropped and named in ``scaling_dropped``. The configs are
bus_limit.py's (config/rover.yaml's wheel settings, nodes 1-N on can0).

``python benchmarks/scaling.py [SECONDS] [--png docs/scaling.png]``: merges the figures into
benchmarks/results.json and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bus_limit
import stack_run
import verdicts
from stack_run import REPO

sys.path.insert(0, str(REPO))
from can_config.bits import frame_bits

DRIVES = (1, 3, 6, 12, 18)
RATES = (100.0, 250.0, 500.0)
OUT = Path(__file__).resolve().parent / "results.json"


def bus_load(drives: int, hz: float) -> float:
    """The share of 1 Mbit/s one cycle's frames take each second, no stuffing (SYNC, RPDO 6 bytes, TPDO2 8, TPDO3 4)."""
    bits = frame_bits(0, worst_case_stuffing=False) + drives * sum(
        frame_bits(n, worst_case_stuffing=False) for n in (6, 8, 4))
    return bits * hz / bus_limit.WIRE_BITRATE


def point(drives: int, hz: float, seconds: float) -> dict[str, Any]:
    """One combination's figures."""
    with bus_limit.limit_config(drives, hz) as config:
        figures = bus_limit.stack(config, seconds, hz)
    cpu = figures["bus_limit_cpu_core_fraction"]
    return {"drives": drives, "hz": hz, "cpu_core_fraction": cpu,
            "cpu_us_per_drive_cycle": round(cpu / (drives * hz) * 1e6, 2),
            "cmd_latency_p99_ms": figures["bus_limit_cmd_latency_p99_ms"],
            "sync_jitter_p99_us": figures["bus_limit_sync_jitter_p99_us"],
            "tpdo_loss": figures["bus_limit_tpdo_loss"], "frames_per_s": figures["bus_limit_frames_per_s"],
            "bus_load": round(bus_load(drives, hz), 3), "not_carried": bus_limit.not_carried(figures, drives, hz)}


def curve(seconds: float) -> dict[str, Any]:
    points: list[dict[str, Any]] = []
    dropped: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    for hz in RATES:
        for drives in DRIVES:
            if bus_load(drives, hz) > 1.0:
                dropped.append({"drives": drives, "hz": hz, "bus_load": round(bus_load(drives, hz), 2)})
                continue
            print(f"scaling: {drives} drives at {hz:g} Hz ...", file=sys.stderr, flush=True)
            for attempt in (1, 2):  # a busy machine can make one start time out: once more
                try:
                    points.append(point(drives, hz, seconds))
                    break
                except RuntimeError as err:
                    print(f"scaling: {drives} drives at {hz:g} Hz failed (run {attempt} of 2): {err}", file=sys.stderr)
            else:
                failed.append({"drives": drives, "hz": hz})
    costs = [p["cpu_us_per_drive_cycle"] for p in points if p["not_carried"] is None]
    out: dict[str, Any] = {"scaling_curve": points, "scaling_dropped": dropped, "scaling_failed": failed,
                           "scaling_seconds": seconds}
    if costs:
        out["scaling_cost_spread"] = round(max(costs) / min(costs) - 1, 2)
    out.update(added_costs(points))
    every = [p["cpu_us_per_drive_cycle"] for p in points]
    if every:  # runs the emulator did not carry too: what the machine gave, no verdict
        out["scaling_cost_spread_all_runs"] = round(max(every) / min(every) - 1, 2)
    # the fit over the runs the emulator carried (as the spread): a run that measured refusals or a
    # starved emulator is not a point of the driver's cost
    out.update(fit([p for p in points if p["not_carried"] is None]))
    return out


def added_costs(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Each run of more than one drive: what the drives beyond the first cost per drive-cycle, against
    the one-drive run at its rate (``added_us_per_drive_cycle``; ``added_carried`` when the emulator
    carried both runs). Returns the largest spread of those within one rate, and them by rate."""
    alone = {p["hz"]: p for p in points if p["drives"] == 1}
    by_rate: dict[float, list[float]] = {}
    for p in points:
        one = alone.get(p["hz"])
        if p["drives"] > 1 and one is not None:
            added = (p["cpu_core_fraction"] - one["cpu_core_fraction"]) / ((p["drives"] - 1) * p["hz"])
            p["added_us_per_drive_cycle"] = round(added * 1e6, 1)
            p["added_carried"] = p["not_carried"] is None and one["not_carried"] is None
            if p["added_carried"]:
                by_rate.setdefault(p["hz"], []).append(p["added_us_per_drive_cycle"])
    spreads = [max(costs) / min(costs) - 1 for costs in by_rate.values() if len(costs) > 1 and min(costs) > 0]
    if not spreads:
        return {}
    return {"scaling_added_cost_spread": round(max(spreads), 2),
            "scaling_added_cost_by_rate": {f"{hz:g}": costs for hz, costs in by_rate.items()}}


def fit(points: list[dict[str, Any]]) -> dict[str, Any]:
    """CPU = fixed + per drive-cycle x drive-cycles/s, least squares over ``points`` (the carried
    runs): the fixed cost (fraction of a core) and the marginal one (us per drive-cycle) that CPU per
    drive-cycle mixes, with the fit's R^2 and the runs it rests on. Fewer than three runs, or all
    at one load: no fit (its verdicts then say "not measured")."""
    xs = [p["drives"] * p["hz"] for p in points]
    if len(set(xs)) < 3:
        return {"scaling_fit_runs": len(points)}
    ys = [p["cpu_core_fraction"] for p in points]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sum((x - mx) ** 2 for x in xs)
    fixed = my - slope * mx
    residual = sum((y - fixed - slope * x) ** 2 for x, y in zip(xs, ys, strict=True))
    spread = sum((y - my) ** 2 for y in ys)
    return {"scaling_fixed_cpu_core_fraction": round(fixed, 3),
            "scaling_marginal_us_per_drive_cycle": round(slope * 1e6, 1),
            "scaling_fit_r2": round(1.0 - residual / spread, 3) if spread > 0 else 0.0, "scaling_fit_runs": len(points)}


def table(out: dict[str, Any]) -> str:
    """The runs, then the fit: CPU = fixed + cost per drive-cycle x drive-cycles/s, with its R^2."""
    lines = ["| drives | Hz | bus load | CPU (core) | CPU per drive-cycle, us | per added drive-cycle, us |"
             " command p99, ms | SYNC p99, us | TPDO loss | carried |", "|---|---|---|---|---|---|---|---|---|---|"]
    for p in out["scaling_curve"]:
        lines.append(f"| {p['drives']} | {p['hz']:g} | {p['bus_load']:.0%} | {p['cpu_core_fraction']} |"
                     f" {p['cpu_us_per_drive_cycle']} | {p.get('added_us_per_drive_cycle', '')} |"
                     f" {p['cmd_latency_p99_ms']} | {p['sync_jitter_p99_us']} | {p['tpdo_loss']} |"
                     f" {p['not_carried'] or 'yes'} |")
    if "scaling_fit_r2" in out:
        lines += ["", "| fit: fixed cost (core) | fit: cost per drive-cycle, us | R^2 | carried runs |",
                  "|---|---|---|---|",
                  f"| {out['scaling_fixed_cpu_core_fraction']} | {out['scaling_marginal_us_per_drive_cycle']} |"
                  f" {out['scaling_fit_r2']} | {out['scaling_fit_runs']} |"]
    return "\n".join(lines)


def plot(out: dict[str, Any], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_cpu, ax_p99) = plt.subplots(1, 2, figsize=(10, 4))
    for hz in RATES:
        pts = [p for p in out["scaling_curve"] if p["hz"] == hz]
        line, = ax_cpu.plot([p["drives"] for p in pts], [p["cpu_us_per_drive_cycle"] for p in pts], "o-", label=f"{hz:g} Hz")
        more = [p for p in pts if "added_us_per_drive_cycle" in p]
        ax_cpu.plot([p["drives"] for p in more], [p["added_us_per_drive_cycle"] for p in more], "s--",
                    color=line.get_color(), label=f"{hz:g} Hz, per added drive-cycle")
        ax_p99.plot([p["drives"] for p in pts], [p["cmd_latency_p99_ms"] for p in pts], "o-", label=f"{hz:g} Hz")
        late = [p for p in pts if p["not_carried"]]  # the emulator did not carry the load: hollow, no verdict
        for ax, key in ((ax_cpu, "cpu_us_per_drive_cycle"), (ax_p99, "cmd_latency_p99_ms")):
            ax.plot([p["drives"] for p in late], [p[key] for p in late], "o", color="white", markersize=4)
    ax_cpu.set(xlabel="drives on one bus", ylabel="CPU per drive-cycle, us", title="driver + ROS node CPU")
    ax_p99.set(xlabel="drives on one bus", ylabel="command p99, ms (log)", title="publish -> RPDO on the wire, p99",
               yscale="log")
    fig.suptitle("hollow: the emulator did not carry the load (no verdict)", fontsize=9)
    for ax in (ax_cpu, ax_p99):
        ax.legend()
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(png, dpi=90)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("seconds", type=float, nargs="?", default=5.0)
    parser.add_argument("--png", type=Path, default=REPO / "docs" / "scaling.png")
    parser.add_argument("--replot", action="store_true", help="only draw the PNG from results.json's curve")
    args = parser.parse_args()
    if args.replot:
        plot(json.loads(OUT.read_text()), args.png)
        return 0
    stack_run.harness_ahead()
    out = {"scaling_date": datetime.now(timezone.utc).isoformat(timespec="seconds"), **curve(args.seconds)}
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    results.update(out)
    OUT.write_text(json.dumps(results, indent=2) + "\n")
    plot(out, args.png)
    print(table(out))
    rows = verdicts.verdicts(out)
    print(f"\n{verdicts.table(rows)}")
    print(f"\nscaling_cost_spread: {out.get('scaling_cost_spread')} (all runs: {out.get('scaling_cost_spread_all_runs')});"
          f" scaling_added_cost_spread: {out.get('scaling_added_cost_spread')};"
          f" fixed {out.get('scaling_fixed_cpu_core_fraction')} of a core + {out.get('scaling_marginal_us_per_drive_cycle')}"
          f" us per drive-cycle (R^2 {out.get('scaling_fit_r2')}); dropped (over one bus): {out['scaling_dropped']};"
          f" failed: {out['scaling_failed']}")
    return verdicts.exit_status(rows, {f"{p['drives']} drives at {p['hz']:g} Hz": "failed" for p in out["scaling_failed"]})


if __name__ == "__main__":
    sys.exit(main())

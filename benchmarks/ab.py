"""Interleaved A/B stack runs of two source trees on one machine (the code before and after a
change): each round runs every shipped config on A and on B, A first in even rounds and B first in
odd ones, so that the machine's drift and whatever the first run leaves behind hit both alike.
Prints each run and the medians as JSON lines.

    python benchmarks/ab.py BEFORE_TREE AFTER_TREE [--rounds 3] [--seconds 10]

Each tree is imported from itself (PYTHONPATH), the venv's other packages are shared.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

FIGURES = ("cmd_latency_p50_ms", "cmd_latency_p99_ms", "cpu_core_fraction", "tpdo_loss", "sync_jitter_p99_us")
RUN = ("import json, sys; sys.path.insert(0, 'benchmarks'); from stack_run import SHIPPED, run_stack;"
       " print('RESULT ' + json.dumps(run_stack(SHIPPED[sys.argv[1]], float(sys.argv[2]), 100.0, tuple(sys.argv[3:]))))")
#: More arguments of `rovercan sim` per config, as benchmarks/run.py runs them.
SIM_ARGS = {"rover": ("--drive-processes",)}


def stack_run(tree: Path, config: str, seconds: float) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    command = [sys.executable, "-c", RUN, config, str(seconds), *SIM_ARGS.get(config, ())]
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, timeout=600)
    if done.returncode:  # say why: a run that fails is a finding, not noise
        raise SystemExit(f"{tree} {config}: the stack run failed ({done.returncode}):\n{done.stderr[-3000:]}")
    out = done.stdout
    result = json.loads(next(line for line in out.splitlines() if line.startswith("RESULT "))[7:])
    figures = {key: value for key, value in result.items() if any(key.endswith(f) for f in FIGURES)}
    # each thread's CPU too: a change to one thread shows there above the whole process's noise
    for name, fraction in result.get("cpu_by_thread", {}).items():
        figures["cpu:" + re.sub(r"@[\d.]+:\d+", "", name)] = fraction  # a bus's port differs per run
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--configs", nargs="+", default=["default", "rover"])
    args = parser.parse_args()
    runs: dict[tuple[str, str], list[dict[str, float]]] = {}
    for round_ in range(args.rounds):
        for config in args.configs:
            pair = (("before", args.before), ("after", args.after))
            for label, tree in pair if round_ % 2 == 0 else pair[::-1]:  # neither always runs second
                result = stack_run(tree.resolve(), config, args.seconds)
                runs.setdefault((config, label), []).append(result)
                print(json.dumps({"round": round_, "config": config, "code": label, **result}), flush=True)
    for (config, label), results in sorted(runs.items()):
        keys = sorted({key for r in results for key in r})  # a thread under 0.002 of a core is left out of a run
        medians = {key: round(statistics.median(r.get(key, 0.0) for r in results), 3) for key in keys}
        spread = {key: [min(r.get(key, 0.0) for r in results), max(r.get(key, 0.0) for r in results)] for key in keys}
        print(json.dumps({"config": config, "code": label, "median": medians, "range": spread}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Which rclpy executor for the driver node? ``python benchmarks/executors.py [--seconds S]``

For each executor (SingleThreaded, MultiThreaded(2), the experimental EventsExecutor) one
process runs a publisher at 100 Hz and a subscriber plus a 50 Hz timer (the shape of the
driver node); it reports publish-to-callback latency (p50/p99, ms) and CPU (fraction of a core).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from std_msgs.msg import Float64

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from rovercan.launch import LOCAL_DISCOVERY

os.environ.setdefault(*LOCAL_DISCOVERY)  # DDS on loopback; the peers it spawns inherit it
from nodes.process.spinning import spin_until


def measure(kind: str, seconds: float) -> dict[str, Any]:
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node(f"bench_{kind}", context=context)
    latencies: list[float] = []
    node.create_subscription(Float64, "/bench", lambda m: latencies.append(time.perf_counter() - m.data), 10)
    node.create_timer(0.02, lambda: None)
    pub = node.create_publisher(Float64, "/bench", 10)
    if kind == "single":
        executor: Any = SingleThreadedExecutor(context=context)
    elif kind == "multi":
        executor = MultiThreadedExecutor(num_threads=2, context=context)
    else:
        from rclpy.experimental import EventsExecutor
        executor = EventsExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()  # stopped the way the nodes stop (nodes/process/spinning.py)
    thread = threading.Thread(target=spin_until, args=(executor, stop), daemon=True)
    thread.start()
    time.sleep(0.5)
    latencies.clear()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    next_t = wall0
    while time.perf_counter() - wall0 < seconds:
        pub.publish(Float64(data=time.perf_counter()))
        next_t += 0.01
        time.sleep(max(0.0, next_t - time.perf_counter()))
    cpu = (time.process_time() - cpu0) / (time.perf_counter() - wall0)
    stop.set()
    thread.join(timeout=2)
    executor.shutdown(timeout_sec=0)
    node.destroy_node()
    rclpy.shutdown(context=context)
    ms = sorted(x * 1000 for x in latencies)
    return {"executor": kind, "callbacks": len(ms), "latency_p50_ms": round(statistics.median(ms), 3),
            "latency_p99_ms": round(ms[int(0.99 * (len(ms) - 1))], 3), "cpu_core_fraction": round(cpu, 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--only", choices=("single", "multi", "events"))
    args = parser.parse_args()
    if args.only:
        print(json.dumps(measure(args.only, args.seconds)))
        return
    results = []
    for kind in ("single", "multi", "events"):  # each in its own process: one may hang
        try:
            out = subprocess.run([sys.executable, __file__, "--only", kind, "--seconds", str(args.seconds)],
                                 capture_output=True, text=True, timeout=args.seconds + 20)
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        except (subprocess.TimeoutExpired, IndexError, json.JSONDecodeError):
            results.append({"executor": kind, "error": "did not finish (hung in spin or shutdown)"})
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()

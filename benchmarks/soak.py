"""Soak: ``python benchmarks/soak.py --minutes 30``.

6 simulated drives, the driver commanding each in profile velocity at 100 Hz, and a fault
injected every few seconds in turn: an EMCY over-current (recover by fault reset), a lost
heartbeat (cable pulled, then plugged back), a power cycle (boot-up, re-configuration). Each
fault must be detected by the driver and recovered. Commands to drives not under a fault are
counted on both ends (sent by the driver, RPDOs received by the simulated drives). Reports
peak RSS growth after warm-up, threads and open file descriptors at start and end, and
writes benchmarks/soak.json. Warm-up ends after the first round of the three fault kinds
(every code path the soak uses has then run once; those faults count like the others); the
growth since the first 5 s of commands is reported beside it. Exits 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from can_config import parse_config, with_bus_overrides  # noqa: E402
from can_config.errors import MotorError  # noqa: E402
from motor_driver import MotorDriver, State  # noqa: E402
from virtual_can import SimService  # noqa: E402
from virtual_can.scenario import apply_action  # noqa: E402

N = 6
FAULT_PERIOD_S = 6.0
RSS_GROWTH_TARGET_MB = 5.0
logging.basicConfig(level=logging.ERROR)
logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def wait(pred: Any, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def inject(sim: SimService, d: Any, node: int, kind: str, boots: int) -> bool:
    """One fault of ``kind`` on ``node``; True when the driver noticed it in time."""
    if kind == "emcy":
        apply_action(sim, {"action": "fault", "node": node, "code": 0x2310})
        return wait(lambda: d.cache.state is State.FAULT and d.snapshot().error_code == 0x2310, 2.0)
    if kind == "unplug":
        apply_action(sim, {"action": "unplug", "node": node})
        ok = wait(lambda: d.cache.lost, 2.0)
        apply_action(sim, {"action": "plug", "node": node})
        return ok
    apply_action(sim, {"action": "power_cycle", "node": node, "off_s": 0.3})
    return wait(lambda: d.boot.boot_count > boots, 5.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    args = parser.parse_args()
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0"}],
                           "drives": [{"name": f"j{i}", "node_id": i, "counts_per_rev": 4096, "watchdog_ms": 500}
                                      for i in range(1, N + 1)]})
    report: dict[str, Any] = {"minutes": args.minutes, "drives": N, "command_rate_hz": 100}
    with SimService.from_config(config, port=0) as sim, \
            MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)) as driver:
        driver.start()
        for d in driver:
            d.enable()
        faulted: set[int] = set()
        sent = [0] * (N + 1)
        stop = threading.Event()
        books = threading.Lock()  # a command is sent and counted, or not at all, as seen by the counting

        def command_loop() -> None:
            k = 0
            next_t = time.monotonic()
            while not stop.is_set():
                k += 1
                for d in driver:
                    with books:
                        if d.node_id in faulted:
                            continue
                        try:
                            d.set_velocity(30.0 + (k % 50))
                            sent[d.node_id] += 1
                        except MotorError:
                            pass
                next_t += 0.01
                time.sleep(max(0.0, next_t - time.monotonic()))

        def rpdos(node: int) -> int:
            """RPDOs the drive received, less the zero-velocity frames the driver's own watchdog sent."""
            s = sim.simulator_for(node)
            received = int(s.call(lambda: s.drive(node).counters["rpdo"]))  # type: ignore[arg-type]
            return received - driver.drive(f"j{node}").limits.watchdog_stops

        time.sleep(1.0)
        threads0, fds0 = threading.active_count(), fds()
        thread = threading.Thread(target=command_loop, daemon=True)
        thread.start()
        time.sleep(5.0)  # commands flowing
        rss_commands = rss_mb()
        rss0 = rss_commands  # until the first round of faults is over
        with books:  # pause every drive's commands, let in-flight ones land, then start counting
            faulted.update(range(1, N + 1))
        time.sleep(0.05)
        with books:
            base = {n: (sent[n], rpdos(n)) for n in range(1, N + 1)}
            faulted.clear()
        faults = {"injected": 0, "detected": 0, "recovered": 0}
        lost_commands = 0
        end = time.monotonic() + args.minutes * 60.0
        kinds = ("emcy", "unplug", "power_cycle")
        i = 0
        while time.monotonic() < end:
            time.sleep(FAULT_PERIOD_S)
            node = i % N + 1
            kind = kinds[i % len(kinds)]
            i += 1
            d = driver.drive(f"j{node}")
            # keep it out of the count while faulted; count its commands once in-flight ones landed
            with books:
                faulted.add(node)
            time.sleep(0.05)  # in-flight commands land
            lost_commands += (sent[node] - base[node][0]) - (rpdos(node) - base[node][1])
            faults["injected"] += 1
            boots = d.boot.boot_count
            faults["detected"] += inject(sim, d, node, kind, boots)
            try:
                if kind == "unplug":
                    wait(lambda d=d: not d.cache.lost, 2.0)
                if kind == "emcy":
                    d.recover()
                d.enable()
                recovered = d.cache.state is State.OPERATION_ENABLED
            except MotorError as err:
                print(f"recovery of j{node} after {kind} failed: {err}", file=sys.stderr)
                recovered = False
            faults["recovered"] += recovered
            with books:
                base[node] = (sent[node], rpdos(node))
                faulted.discard(node)
            if i == len(kinds):  # each fault kind has run once: warm-up is over
                rss0 = rss_mb()
        stop.set()
        thread.join(2)
        time.sleep(0.2)
        for n in range(1, N + 1):
            lost_commands += (sent[n] - base[n][0]) - (rpdos(n) - base[n][1])
        report.update({
            "commands_sent": sum(sent), "commands_lost": lost_commands,
            "faults_injected": faults["injected"], "faults_detected": faults["detected"],
            "faults_recovered": faults["recovered"],
            "watchdog_stops": sum(d.limits.watchdog_stops for d in driver),
            "rss_growth_mb": round(rss_mb() - rss0, 2), "rss_peak_mb": round(rss_mb(), 1),
            "rss_growth_since_first_commands_mb": round(rss_mb() - rss_commands, 2),
            "threads_start": threads0, "threads_end": threading.active_count(),
            "fds_start": fds0, "fds_end": fds(),
        })
    out = Path(__file__).resolve().parent / "soak.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    ok = (report["commands_lost"] == 0 and faults["detected"] == faults["injected"] == faults["recovered"]
          and report["threads_end"] == report["threads_start"] and report["fds_end"] == report["fds_start"]
          and report["rss_growth_mb"] <= RSS_GROWTH_TARGET_MB)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

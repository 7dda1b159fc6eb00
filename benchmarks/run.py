"""Benchmark suite (figures, not pass/fail tests): ``python benchmarks/run.py [--quick]``.

Writes ``benchmarks/results.json``: emulator throughput (in-process; socketcand between two
client processes, loss and order checked), wire-time cap, expedited SDO round trip, boot of 6
drives to Operation Enabled, and the 6-drive stack run (benchmarks/stack_run.py): command
latency against the bare rclpy+python-can path, TPDO loss, CPU and peak RSS of the measured
process, SYNC jitter, and the canopen-library baseline of the same state run; the bus server's
memory after rounds of never-reading clients and floods (benchmarks/server_memory.py); a 10 ms
SYNC's period error beside another client's 65,536 idle cyclic jobs, between its bus times and
between its arrivals at another client (benchmarks/cyclic_jobs.py);
the bus at its limit, six drives on one bus at 500 Hz CSP (benchmarks/bus_limit.py).

Ends with a table of figure / value / target / verdict (benchmarks/verdicts.py): a baseline the
machine made invalid is run once more, then its figures get "no verdict: REASON". Exit status 1
only when a valid measurement missed its target; 2 when a benchmark crashed; 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import can
import canopen

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from rovercan.launch import LOCAL_DISCOVERY

os.environ.setdefault(*LOCAL_DISCOVERY)  # DDS on loopback; the peers it spawns inherit it
# a DDS domain of the run's own (unless one is set): another graph on this machine in the default
# domain (a test's rover_driver) shares the wheels' topic names and /diagnostics, and its counts
# or commands would be taken for the measured process's
os.environ.setdefault("ROS_DOMAIN_ID", str(70 + os.getpid() % 30))

from can_config import GENERIC_EDS, load_config, parse_config, with_bus_overrides
from motor_driver import MotorDriver
from nodes.process.params import PARAMS
from virtual_can import BusEngine, SimService, SocketcandServer, VirtualBus

sys.path.insert(0, str(Path(__file__).resolve().parent))
from verdicts import TARGETS, InvalidBaseline, exit_status, rclpy_canopen_ratio, table, verdicts

logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
OUT = Path(__file__).resolve().parent / "results.json"



def bench_server_memory(quick: bool) -> dict[str, Any]:
    import server_memory

    return server_memory.measure(2 if quick else server_memory.ROUNDS, 100_000 if quick else server_memory.FLOOD_FRAMES)


def bench_cyclic_jobs(seconds: float) -> dict[str, Any]:
    import cyclic_jobs

    return cyclic_jobs.measure(cyclic_jobs.IDLE_JOBS, seconds)


def measured(out: dict[str, Any], errors: dict[str, str], name: str, fn: Callable[..., dict[str, Any]],
             *args: Any) -> None:
    """``out`` updated with one benchmark's figures; one that fails goes into ``errors`` (and is
    said), and the others still run: a failing baseline at the end of a 15-minute run must not
    take every other figure with it."""
    try:
        out.update(fn(*args))
    except Exception as err:  # recorded, and main() exits 1
        errors[name] = f"{type(err).__name__}: {err}"
        print(f"benchmark {name} FAILED: {type(err).__name__}: {err}", file=sys.stderr, flush=True)


def validated(out: dict[str, Any], invalid: dict[str, str], errors: dict[str, str], name: str,
              fn: Callable[..., dict[str, Any]], *args: Any) -> None:
    """A baseline that validates itself (raises InvalidBaseline when the machine made it late): run
    once more when it was invalid, and still invalid, its reason goes into ``invalid`` (the figures
    resting on it get no verdict, verdicts.py). One that failed otherwise is run once more too (a
    busy machine can time a start out); failing again, it goes into ``errors``."""
    for attempt in (1, 2):
        try:
            out.update(fn(*args))
            invalid.pop(name, None)
            errors.pop(name, None)
            return
        except InvalidBaseline as err:
            invalid[name] = str(err)
            print(f"baseline {name} invalid (run {attempt} of 2): {err}", file=sys.stderr, flush=True)
        except Exception as err:  # recorded, and main() exits 2
            errors[name] = f"{type(err).__name__}: {err}"
            print(f"benchmark {name} FAILED (run {attempt} of 2): {type(err).__name__}: {err}", file=sys.stderr,
                  flush=True)


def more_pairs(pairs: int, stack_cpu: Callable[[], float], base_cpu: Callable[[], float | None],
               dropped_key: str) -> dict[str, Any]:
    """``pairs`` more pairs of a stack run's CPU (``stack_cpu``) and the canopen same work's
    (``base_cpu``; None: invalid twice), each pair side by side and every other one in the other
    order; their ratios (``more_pairs``). A CPU ratio is the median of these and the main runs'
    pair. A busy machine's load drifts over the minutes between a run's first and last benchmark,
    and the driver's process (more threads woken) and the library's take it differently; one
    pair, minutes apart, moved the ratio by a third (2.0 and 3.5 on one day; six drives at 500 Hz
    1.75 and 1.40 in one run). ``dropped_key`` counts the pairs that gave no ratio: a baseline
    invalid twice, a run that did not start or was not carried (``stack_cpu`` raises), any
    failure of one pair (said; the others still run)."""
    ratios = []
    dropped = 0
    for i in range(pairs):
        try:
            if i % 2:
                stack = stack_cpu()
                base = base_cpu()
            else:  # the base first: the first pair (the main runs) had the stack run first
                base = base_cpu()
                stack = stack_cpu()
        except Exception as err:  # a run that did not start or was not carried, a helper's timeout: no pair
            print(f"CPU ratio pair {i + 1} dropped: {type(err).__name__}: {err}", file=sys.stderr, flush=True)
            base = None
        if base is None:
            dropped += 1  # a pair without a valid baseline is no ratio
        else:
            ratios.append(stack / base)
    return {"more_pairs": ratios, dropped_key: dropped}


def baseline_cpu(config: Path, seconds: float, hz: float, priority: int) -> float | None:
    """The canopen same work's CPU on ``config``, run once more when the machine made it invalid;
    None when still invalid."""
    import same_work

    for _ in (1, 2):
        try:
            return float(same_work.baseline_same_work(config, seconds, hz, priority)
                         ["baseline_canopen_same_work_rt_cpu_core_fraction"])
        except InvalidBaseline as err:
            print(f"baseline of a CPU ratio pair invalid: {err}", file=sys.stderr, flush=True)
    return None


def judged_stack_run(config: Path, seconds: float, hz: float) -> tuple[dict[str, Any], str | None]:
    """A stack run on ``config`` (bus_limit.stack: its listener on can0 counting what the emulator
    carried) and why its figures do not count (bus_limit.not_carried over can0's drives), or None."""
    import bus_limit

    out = bus_limit.stack(config, seconds, hz, prefix="")
    drives = sum(1 for d in load_config(config).drives if d.bus == "can0")
    return out, bus_limit.not_carried(out, drives, hz, prefix="")


def carried_cpu(config: Path, seconds: float, hz: float) -> float:
    """A stack run's CPU (:func:`judged_stack_run`), RuntimeError when the emulator did not carry
    the load: a starved run measures less work, and a ratio from it would be low for no merit of
    the driver's."""
    out, reason = judged_stack_run(config, seconds, hz)
    if reason is not None:
        raise RuntimeError(f"the emulator did not carry the stack run: {reason}")
    return float(out["cpu_core_fraction"])


def cpu_ratio_pairs(pairs: int, seconds: float, priority: int) -> dict[str, Any]:
    """The shipped rover's more pairs (:func:`more_pairs`)."""
    import stack_run

    shipped = stack_run.SHIPPED["rover"]
    return more_pairs(pairs, lambda: carried_cpu(shipped, seconds, 100.0),
                      lambda: baseline_cpu(shipped, seconds, 100.0, priority), "cpu_ratio_canopen_pairs_dropped_invalid")


def with_median(out: dict[str, Any], key: str, first: float, more: list[float]) -> None:
    """``key`` the median of the main runs' ratio ``first`` and ``more`` pairs', ``key``_pairs them all."""
    ratios = [first, *more]
    out[f"{key}_pairs"] = [round(r, 2) for r in ratios]
    out[key] = round(statistics.median(ratios), 2)


def carried_stack_run(seconds: float, invalid: dict[str, str]) -> dict[str, Any]:
    """The rover's stack run, once more when the emulator did not carry its SYNC and TPDOs (the
    machine starved it: bus_limit.not_carried); still not, the reason goes into ``invalid`` and the
    figures resting on it get no verdict."""
    import bus_limit
    import stack_run

    runs = stack_run.two_tries("stack run", "stack run: emulator", invalid, "",
                               lambda: judged_stack_run(stack_run.SHIPPED["rover"], seconds, 100.0))
    out = runs[-1]
    out.update(bus_limit.every_stop(runs, prefix=""))
    return out


def bench_stack(seconds: float, pairs: int, errors: dict[str, str], invalid: dict[str, str]) -> dict[str, Any]:
    import same_work
    import stack_run

    # the six-drive twin as docs/performance.md says to run it: each bus's drive models in a
    # process of their own, so the server's SYNC timer waits for none of them (issue 43)
    out = carried_stack_run(seconds, invalid)
    priority = int(PARAMS["realtime_priority"].default)  # type: ignore[call-overload]
    # the "canopen baseline, same work": the canopen library doing the stack run's CAN work
    # (the shipped config's two buses, the same PDOs, SYNC, every drive enabled in CSP and sent the
    # same ramp by RPDO at 100 Hz), its threads scheduled as the node's, measured right after the
    # stack run; then more such pairs, each in the other order (cpu_ratio_pairs)
    validated(out, invalid, errors, "canopen same work", same_work.baseline_same_work, stack_run.SHIPPED["rover"], seconds,
              100.0, priority)
    base = out.get("baseline_canopen_same_work_rt_cpu_core_fraction")  # the CPU ratios' reference
    # the same set-points as one /joint_commands JointState a tick (ros2_control's topic-based
    # hardware interface), right after the baseline: what a sixth of the ROS messages costs (reference)
    joint_commands: dict[str, Any] = {}
    measured(joint_commands, errors, "stack run, /joint_commands", stack_run.run_stack, stack_run.SHIPPED["rover"],
             seconds, 100.0, ("--drive-processes",), True)
    out.update({f"joint_commands_{k}": v for k, v in joint_commands.items() if k != "config"})
    if joint_commands.get("cpu_core_fraction") and base:
        out["cpu_ratio_canopen_joint_commands"] = round(joint_commands["cpu_core_fraction"] / base, 2)
    default: dict[str, Any] = {}
    measured(default, errors, "stack run, embedded default", stack_run.run_stack, stack_run.SHIPPED["default"],
             min(seconds, 10.0), 100.0)
    out.update({f"default_{k}": v for k, v in default.items()})
    # the bare path as the node runs (its threads under SCHED_FIFO: realtime_priority, the default),
    # the ratio's reference; and ordinary, as it was measured before the node went real-time
    measured(out, errors, "bare path", stack_run.bare_path, min(seconds, 10.0), 1, priority)
    measured(out, errors, "bare path, same burst", stack_run.bare_path, min(seconds, 10.0), out["drives"], priority)
    measured(out, errors, "bare path, ordinary", stack_run.bare_path, min(seconds, 10.0))
    burst = f"bare_rt_latency_{out['drives']}_topics_p50_ms"
    if out.get("cmd_latency_p50_ms") and out.get("bare_rt_latency_p50_ms"):
        out["cmd_latency_ratio"] = round(out["cmd_latency_p50_ms"] / out["bare_rt_latency_p50_ms"], 2)
    if out.get("cmd_latency_p50_ms") and out.get("bare_latency_p50_ms"):
        out["cmd_latency_ratio_ordinary_bare"] = round(out["cmd_latency_p50_ms"] / out["bare_latency_p50_ms"], 2)
    if out.get("cmd_latency_p50_ms") and out.get(burst):
        out["cmd_latency_ratio_same_burst"] = round(out["cmd_latency_p50_ms"] / out[burst], 2)
    validated(out, invalid, errors, "canopen state run", stack_run.baseline_canopen, 6, 10.0, seconds)
    validated(out, invalid, errors, "driver alone, state run", stack_run.driver_only, 6, 10.0, seconds)
    validated(out, invalid, errors, "canopen same work, ordinary", same_work.baseline_same_work,
              stack_run.SHIPPED["rover"], min(seconds, 10.0), 100.0)
    state_base = out.get("baseline_canopen_cpu_core_fraction")
    if out.get("cpu_core_fraction") and base:
        measured(out, errors, "CPU ratio pairs", cpu_ratio_pairs, pairs, min(seconds, 20.0), priority)
        with_median(out, "cpu_ratio_canopen", out["cpu_core_fraction"] / base, out.pop("more_pairs", []))
    if out.get("cpu_core_fraction") and state_base:
        # the ratio as first measured: against the canopen library's state run (one bus, no commands)
        out["cpu_ratio_canopen_state_run"] = round(out["cpu_core_fraction"] / state_base, 2)
    # a node of rclpy and the canopen library, in parts (a reference, not a lower bound: this driver's
    # receive path costs less than the library's): rclpy's own cost for the commands (the bare path,
    # one frame sent per command) plus the canopen library's for the state (its state run), over the
    # canopen library's same work (its main pair's: measured minutes apart, so as noisy as one pair)
    with_rclpy_canopen(out, "cpu_floor_ratio_canopen", out, out["drives"], state_base, base)
    return out


def with_rclpy_canopen(out: dict[str, Any], key: str, bare: dict[str, Any], drives: int, state: float | None,
                       base: float | None) -> None:
    """``out[key]``: :func:`verdicts.rclpy_canopen_ratio` of the bare path's figures in ``bare``
    (``drives`` topics, SCHED_FIFO), when it gives one."""
    ratio = rclpy_canopen_ratio(bare.get(f"bare_rt_{drives}_topics_cpu_core_fraction"),
                                bare.get(f"bare_rt_{drives}_topics_delivered"), state, base)
    if ratio is not None:
        out[key] = ratio


def bench_bus_limit(seconds: float, pairs: int, errors: dict[str, str], invalid: dict[str, str]) -> dict[str, Any]:
    """Six drives on one bus at 500 Hz CSP (bus_limit.py) beside the canopen library's same work;
    its CPU ratio the median of that pair and ``pairs`` more (:func:`more_pairs`), as the rover's."""
    import bus_limit
    import follow_trajectory
    import same_work
    import stack_run

    priority = int(PARAMS["realtime_priority"].default)  # type: ignore[call-overload]
    with bus_limit.limit_config() as config:
        def one_run() -> tuple[dict[str, Any], str | None]:
            run = bus_limit.stack(config, seconds)
            return run, bus_limit.not_carried(run)

        runs = stack_run.two_tries("bus limit", "bus limit: emulator", invalid, "bus_limit_", one_run)
        out = runs[-1]
        out.update(bus_limit.every_stop(runs))
        base: dict[str, Any] = {}
        validated(base, invalid, errors, "bus limit: canopen same work", same_work.baseline_same_work, config, seconds,
                  bus_limit.HZ, priority)
        # reference: the same set-points as one /joint_commands message a SYNC
        joint_commands: dict[str, Any] = {}
        measured(joint_commands, errors, "bus limit, /joint_commands", bus_limit.stack, config, seconds, bus_limit.HZ,
                 "bus_limit_joint_commands_", "can0", True)
        out.update(bus_limit.ratio(out, base))
        if "bus_limit_cpu_ratio_canopen" in out:
            more: dict[str, Any] = {}
            measured(more, errors, "bus limit: CPU ratio pairs", more_pairs, pairs,
                     lambda: carried_cpu(config, seconds, bus_limit.HZ),
                     lambda: baseline_cpu(config, seconds, bus_limit.HZ, priority),
                     "bus_limit_cpu_ratio_canopen_pairs_dropped_invalid")
            out.update({k: v for k, v in more.items() if k != "more_pairs"})
            with_median(out, "bus_limit_cpu_ratio_canopen", out["bus_limit_cpu_core_fraction"]
                        / base["baseline_canopen_same_work_rt_cpu_core_fraction"], more.get("more_pairs", []))
        # reference: the same six drives following one FollowJointTrajectory goal, each set-point
        # sampled by the driver at its SYNC (no ROS message a set-point, as the canopen library's run)
        trajectory: dict[str, Any] = {}
        measured(trajectory, errors, "bus limit, trajectory", follow_trajectory.six_following, seconds)
    base_cpu = base.get("baseline_canopen_same_work_rt_cpu_core_fraction")
    out.update(joint_commands)
    if joint_commands.get("bus_limit_joint_commands_cpu_core_fraction") and base_cpu:
        out["bus_limit_cpu_ratio_canopen_joint_commands"] = round(
            joint_commands["bus_limit_joint_commands_cpu_core_fraction"] / base_cpu, 2)
    out.update({f"bus_limit_trajectory_{k}": v for k, v in trajectory.items()})
    if trajectory.get("periods_none", 1.0) > bus_limit.SETPOINT_LOSS_MAX:  # the work not done: no figure
        invalid["bus limit, trajectory"] = (f"the trajectory run's joints got no set-point in"
                                            f" {trajectory.get('periods_none', 1.0):.1%} of the SYNC periods")
    elif trajectory.get("cpu_core_fraction") and base_cpu:
        out["bus_limit_cpu_ratio_canopen_trajectory"] = round(trajectory["cpu_core_fraction"] / base_cpu, 2)
    # a node of rclpy and the canopen library, in parts, as the rover's (bench_stack): rclpy taking the
    # same 3,000 Float32 a second, one python-can send each, plus the canopen library's state run of
    # six drives at 500 Hz
    floor: dict[str, Any] = {}
    short = min(seconds, 10.0)
    measured(floor, errors, "bus limit: bare path", stack_run.bare_path, short, bus_limit.DRIVES, priority, bus_limit.HZ)
    validated(floor, invalid, errors, "bus limit: canopen state run", stack_run.baseline_canopen, bus_limit.DRIVES,
              1000.0 / bus_limit.HZ, short)
    out.update({f"bus_limit_{k}": v for k, v in floor.items()})
    with_rclpy_canopen(out, "bus_limit_cpu_floor_ratio_canopen", floor, bus_limit.DRIVES,
                       floor.get("baseline_canopen_cpu_core_fraction"), base_cpu)
    return out


def flood(tx: can.BusABC, rx: can.BusABC, n: int) -> tuple[float, int, bool]:
    """Send n 8-byte frames from tx; count and order-check them at rx. Returns (fps, received, in_order)."""
    got: list[int] = []
    done = threading.Event()

    def reader() -> None:
        while len(got) < n:
            msg = rx.recv(2.0)
            if msg is None:
                break
            got.append(int.from_bytes(msg.data, "little"))
        done.set()

    thread = threading.Thread(target=reader)
    thread.start()
    start = time.perf_counter()
    for i in range(n):
        tx.send(can.Message(arbitration_id=0x181, data=i.to_bytes(8, "little"), is_extended_id=False))
    done.wait()
    elapsed = time.perf_counter() - start
    thread.join()
    return len(got) / elapsed, len(got), got == list(range(len(got)))


def bench_inprocess(n: int) -> dict[str, Any]:
    with BusEngine() as engine:
        a, b = VirtualBus("can0", engine=engine), VirtualBus("can0", engine=engine)
        fps, received, ordered = flood(a, b, n)
        a.shutdown()
        b.shutdown()
    return {"emulator_fps_inprocess": round(fps), "emulator_inprocess_lost": n - received,
            "emulator_inprocess_in_order": ordered}


def bench_socketcand(seconds: float, rate: float = 10_000.0) -> dict[str, Any]:
    """Two client processes (python-can's socketcand client) through the server: a sender paced
    at ``rate`` (above a saturated 1 Mbit/s bus: 9,009 frames/s) and a receiver that checks
    loss and order."""
    n = int(seconds * rate)
    peer = [sys.executable, str(Path(__file__).resolve().parent / "socketcand_peer.py")]
    with BusEngine() as engine, SocketcandServer(engine, port=0) as srv:
        recv = subprocess.Popen([*peer, "recv", srv.host, str(srv.port), str(n)], stdout=subprocess.PIPE, text=True)
        send = subprocess.Popen([*peer, "send", srv.host, str(srv.port), str(n), str(rate)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert recv.stdout is not None and send.stdout is not None and send.stdin is not None
        recv.stdout.readline()
        send.stdout.readline()
        send.stdin.write("go\n")
        send.stdin.flush()
        sent = json.loads(send.stdout.readline())
        got = json.loads(recv.stdout.readline())
        send.wait(10)
        recv.wait(10)
    return {"emulator_fps_socketcand": round(min(sent["send_fps"], got["recv_fps"])),
            "emulator_socketcand_frames": n, "emulator_socketcand_lost": got["lost"],
            "emulator_socketcand_out_of_order": got["out_of_order"]}


def bench_wire_time(n: int) -> dict[str, Any]:
    with BusEngine(wire_time=True, bitrate=1_000_000) as engine:
        a, b = VirtualBus("can0", engine=engine), VirtualBus("can0", engine=engine)
        fps, _, _ = flood(a, b, n)
        load = engine.channel("can0").load()
        a.shutdown()
        b.shutdown()
    return {"wire_time_fps_1mbit": round(fps), "wire_time_bus_load": round(load, 3)}


def bench_sdo(n: int) -> dict[str, Any]:
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0"}],
                           "drives": [{"name": "j1", "node_id": 1}]})
    with SimService.from_config(config, port=0) as sim:
        bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port, tcp_tune=True)
        network = canopen.Network(bus)
        network.connect()
        node = network.add_node(1, str(GENERIC_EDS))
        rtts = []
        for _ in range(n):
            t0 = time.perf_counter()
            node.sdo.upload(0x6041, 0)
            rtts.append((time.perf_counter() - t0) * 1000)
        network.disconnect()
    rtts.sort()
    return {"sdo_rtt_p50_ms": round(statistics.median(rtts), 3),
            "sdo_rtt_p99_ms": round(rtts[int(0.99 * (len(rtts) - 1))], 3)}


def bench_boot(runs: int) -> dict[str, Any]:
    """The shipped rover config's six wheels (two buses) from NMT reset to Operation Enabled."""
    config = load_config(Path(__file__).resolve().parent.parent / "config" / "rover.yaml")
    times = []
    with SimService.from_config(config, port=0) as sim:
        cfg = with_bus_overrides(config, host=sim.host, port=sim.port)
        for _ in range(runs):
            with MotorDriver(cfg) as driver:
                t0 = time.perf_counter()
                driver.start()
                for drive in driver:
                    drive.enable()
                times.append(time.perf_counter() - t0)
    return {"boot_6_drives_s": round(statistics.median(times), 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="short version (about 4 minutes)")
    args = parser.parse_args()
    # the flight recorder of the measured drivers writes the runs' incidents (the drives' host-loss
    # EMCYs when a run ends) here, not into the user's ~/.local/state
    os.environ.setdefault("ROVERCAN_INCIDENT_DIR", tempfile.mkdtemp(prefix="rovercan-bench-incidents-"))
    scale = 1 if args.quick else 10
    import stack_run

    results: dict[str, Any] = {
        "harness_nice": stack_run.harness_ahead(), "harness_fifo_priority": stack_run.harness_priority(),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mode": "quick" if args.quick else "full",
        "machine": {"platform": platform.platform(), "processor": platform.machine(),
                    "python": platform.python_version()},
        "versions": {"python-can": can.__version__, "canopen": canopen.__version__},
    }
    errors: dict[str, str] = {}
    for name, fn, arg in (("in-process bus", bench_inprocess, 100_000 * scale),
                          ("socketcand server, two client processes", bench_socketcand, 5.0 if args.quick else 60.0),
                          ("wire time", bench_wire_time, 5_000 * scale),
                          ("SDO round trip", bench_sdo, 500 * scale),
                          ("boot 6 drives", bench_boot, 3),
                          ("bus server memory under silent clients and floods", bench_server_memory, args.quick),
                          ("another client's SYNC beside 65,536 idle cyclic jobs", bench_cyclic_jobs,
                           5.0 if args.quick else 30.0)):
        print(f"benchmark: {name} ...", flush=True)
        measured(results, errors, name, fn, arg)
    print("benchmark: stack runs on config/rover.yaml and the embedded default (driver + ROS node,"
          " listener, baselines) ...", flush=True)
    invalid: dict[str, str] = {}
    measured(results, errors, "stack run, config/rover.yaml", bench_stack, 10.0 if args.quick else 60.0,
             2 if args.quick else 4, errors, invalid)
    print("benchmark: the bus at its limit (six drives on one bus, 500 Hz CSP) ...", flush=True)
    measured(results, errors, "bus limit", bench_bus_limit, 10.0 if args.quick else 30.0, 2 if args.quick else 4, errors,
             invalid)
    if errors:
        results["errors"] = errors
    if invalid:
        results["invalid"] = invalid
    results["targets"] = {k: list(v) for k, v in TARGETS.items()}
    rows = verdicts(results)
    results["verdicts"] = [row._asdict() for row in rows]
    # the scaling curve is scaling.py's (minutes, not part of this run; it gives its own verdicts):
    # its last figures stay in the file beside this run's
    try:
        before = json.loads(OUT.read_text())
    except (OSError, ValueError):  # none yet, or not readable: this run's figures all the same
        before = {}
    results.update({k: v for k, v in before.items() if k.startswith("scaling_")})
    OUT.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    print(f"\n{table(rows)}")
    if errors:
        print(f"benchmarks that failed (results.json has the rest): {', '.join(errors)}", file=sys.stderr)
    return exit_status(rows, errors)


if __name__ == "__main__":
    sys.exit(main())

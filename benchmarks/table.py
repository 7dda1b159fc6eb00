"""Print the README's performance table from benchmarks/results.json: ``python benchmarks/table.py``."""

from __future__ import annotations

import json
from pathlib import Path

ROWS = [
    ("cmd_latency_p50_ms", "command latency p50 (publish -> RPDO on the wire), ms", "<= 0.5", "bare_rt_latency_p50_ms"),
    ("cmd_latency_p99_ms", "command latency p99, ms", "<= 2", None),
    ("cmd_latency_ratio", "p50 / bare path (rclpy + one python-can send, SCHED_FIFO as the node)", "<= 1.3", None),
    ("cmd_latency_ratio_ordinary_bare", "p50 / bare path with ordinary scheduling", "", "bare_latency_p50_ms"),
    ("cmd_latency_ratio_same_burst", "p50 / bare path with the same burst (six topics, six sends every 10 ms)", "",
     "bare_rt_latency_6_topics_p50_ms"),
    ("cmd_latency_p50_ms_by_publish_order", "command latency p50 by place in the burst (1st .. 6th joint), ms", "", None),
    ("cmd_latency_p50_ms_by_sync_phase", "command latency p50 by when it was published after a SYNC (tenths of the period), ms",
     "", None),
    ("default_cmd_latency_p50_ms", "embedded default (1 motor): command latency p50, ms", "<= 0.5", None),
    ("default_cmd_latency_p99_ms", "embedded default (1 motor): command latency p99, ms", "<= 2", None),
    ("tpdo_loss", "TPDO loss, 6 drives, 100 Hz SYNC", "0", "baseline_canopen_tpdo_loss"),
    ("cpu_core_fraction", "CPU of driver + ROS node process (fraction of a core)", "<= 0.15",
     "baseline_canopen_cpu_core_fraction"),
    ("baseline_canopen_same_work_rt_cpu_core_fraction", "CPU of the canopen library doing the same CAN work (two buses,"
     " the same PDOs, SYNC, 600 CSP RPDOs/s), SCHED_FIFO as the node", "", "baseline_canopen_same_work_cpu_core_fraction"),
    ("cpu_ratio_canopen", "CPU of driver + ROS node / the canopen library's same work, same run: the median of"
     " pairs run side by side", "<= 2.5", None),
    ("cpu_ratio_canopen_pairs", "each pair's ratio (the first: the main 60 s runs; the others 20 s, in turn base first)",
     "", None),
    ("cpu_ratio_canopen_state_run", "the same over the canopen library's state run (one bus, no commands: the first"
     " measure)", "", None),
    ("cpu_floor_ratio_canopen", "a node of rclpy and the canopen library, in parts: (rclpy taking the same commands,"
     " one send each + the canopen library's state run) / its same work (a reference, not a lower bound)", "",
     "bare_rt_6_topics_cpu_core_fraction"),
    ("driver_only_cpu_core_fraction", "CPU of the driver alone, same state run", "", "baseline_canopen_cpu_core_fraction"),
    ("sync_jitter_p99_us", "SYNC period error p99 at a listener, us", "<= 200", None),
    ("sync_delivery_p99_us", "SYNC heard by a client (the listener) after its bus time, p99, us", "",
     "tpdo_delivery_p99_us"),
    ("default_sync_jitter_p99_us", "embedded default (1 motor): SYNC period error p99, us", "<= 200", None),
    ("sync_timer_realtime", "the simulator's SYNC timer process ran under SCHED_FIFO (can_config/realtime.py)", "", None),
    ("host_heartbeat_gap_max_ms", "driver's heartbeat (50 ms) longest gap at a listener, ms", "< 150 (consumer)", None),
    ("boot_6_drives_s", "6 drives from NMT reset to Operation Enabled, s", "<= 1.0", None),
    ("sdo_rtt_p99_ms", "expedited SDO upload round trip p99, ms", "<= 5", None),
    ("emulator_fps_socketcand", "socketcand server, 2 client processes, frames/s (0 lost)", ">= 9,009", None),
    ("emulator_fps_inprocess", "in-process bus, frames/s (0 lost)", ">= 90,000", None),
    ("wire_time_fps_1mbit", "wire-time mode, flooded 1 Mbit/s bus, frames/s", "< 9,009", None),
    ("rss_mb", "peak RSS of driver + ROS node process, MB", "<= 150", None),
    ("server_rss_growth_mb", "bus server RSS growth after 6 x (40 never-reading clients + 400k frames), MB", "<= 10",
     None),
    ("server_rss_peak_mb", "bus server peak RSS in that run, MB", "", None),
    ("cyclic_sync_error_p99_ms", "a 10 ms SYNC beside another client's 65,536 idle cyclic jobs, period error p99"
     " between bus times, ms", "< 1", "cyclic_sync_error_p99_ms_no_jobs"),
    ("cyclic_sync_arrival_error_p99_ms", "the same measured from outside: between its arrivals at another client, ms",
     "< 1", "cyclic_sync_arrival_error_p99_ms_no_jobs"),
    ("bus_limit_tpdo_loss", "bus at its limit (6 drives, one bus, 500 Hz CSP): TPDO loss", "0", None),
    ("bus_limit_setpoint_loss_fraction", "bus at its limit: set-point loss (commands published that never went on"
     " the wire as a set-point), fraction", "", None),
    ("bus_limit_cpu_ratio_canopen", "bus at its limit: CPU of driver + ROS node / the canopen library's same work",
     "<= 2", "bus_limit_baseline_canopen_same_work_rt_cpu_core_fraction"),
    ("bus_limit_cpu_floor_ratio_canopen", "bus at its limit: a node of rclpy and the canopen library, in parts (rclpy"
     " taking the same 3,000 commands/s, one send each + the canopen library's state run at 500 Hz) / its same work",
     "", "bus_limit_bare_rt_6_topics_cpu_core_fraction"),
    ("bus_limit_cmd_latency_p99_ms", "bus at its limit: command latency p99, ms", "<= 2", None),
    ("bus_limit_sync_jitter_p99_us", "bus at its limit: SYNC period error p99, us", "<= 200", None),
    ("bus_limit_frames_per_s", "bus at its limit: frames/s the emulator carried (9,500 due)", "", "bus_limit_bus_load"),
    ("scaling_cost_spread", "CPU per drive-cycle, largest / smallest - 1 (1-18 drives, 100-500 Hz)", "<= 0.2", None),
]


def main() -> None:
    data = json.loads((Path(__file__).resolve().parent / "results.json").read_text())
    print(f"Measured {data['date']} ({data['mode']} run), Python {data['machine']['python']},"
          f" python-can {data['versions']['python-can']}, canopen {data['versions']['canopen']}.\n")
    print(f"Stack runs on `{data.get('config')}` ({data.get('drives')} drives) and on the embedded default, as shipped"
          " (only the simulator's port put in).\n")
    print("| figure | ours | target | baseline |\n|---|---|---|---|")
    for key, what, target, base in ROWS:
        baseline = data.get(base) if base else None
        label = {"bare_rt_latency_p50_ms": "bare path", "bare_rt_latency_6_topics_p50_ms": "bare path, 6 topics",
                 "bare_latency_p50_ms": "bare path, ordinary",
                 "baseline_canopen_tpdo_loss": "canopen lib",
                 "baseline_canopen_cpu_core_fraction": "canopen lib, state run",
                 "baseline_canopen_same_work_cpu_core_fraction": "ordinary scheduling",
                 "cyclic_sync_error_p99_ms_no_jobs": "no idle jobs",
                 "cyclic_sync_arrival_error_p99_ms_no_jobs": "no idle jobs",
                 "bare_rt_6_topics_cpu_core_fraction": "bare path's CPU, 6 topics", "tpdo_delivery_p99_us": "a TPDO",
                 "bus_limit_baseline_canopen_same_work_rt_cpu_core_fraction": "canopen lib's CPU",
                 "bus_limit_bare_rt_6_topics_cpu_core_fraction": "bare path's CPU, 6 topics at 500 Hz",
                 "bus_limit_bus_load": "bus load"}.get(base or "", "")
        print(f"| {what} | {data.get(key)} | {target} | {f'{baseline} ({label})' if baseline is not None else ''} |")


if __name__ == "__main__":
    main()

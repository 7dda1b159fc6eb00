"""The 6-drive stack run of the performance issue, measured from outside the measured process.

The simulator (socketcand server + 6 drives) runs in this process; the measured process is
``rover_driver`` (driver + ROS node) in its own process; an independent listener (a python-can
socketcand client here) sees every frame with the server's wire timestamp. Figures:

* cmd_latency: publish on ``<joint>/degree_cmd`` (6 joints at 100 Hz) -> the RPDO with that
  target on the wire; the bare path (rclpy publish -> a subscriber process on the
  EventsExecutor the node uses -> one python-can send) is measured the same way.
* tpdo_loss: TPDOs the simulated drives sent minus TPDOs the driver applied (its count comes
  over /diagnostics), after the drives stop sending.
* cpu_core_fraction, rss_mb: /proc of the measured process (CPU time / wall time; VmHWM).
* sync_jitter_p99_us: SYNC period error at the listener.
* baseline: the same state run done the canopen library's way (BaseNode402 + PDO callbacks).
"""

from __future__ import annotations

import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from rovercan.launch import LOCAL_DISCOVERY  # noqa: E402

os.environ.setdefault(*LOCAL_DISCOVERY)  # DDS on loopback; the peers it spawns inherit it

from virtual_can import SimDriveSpec, SimService  # noqa: E402

COUNTS_PER_DEG = 4096 / 360.0


def proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_rss_peak_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * (len(ordered) - 1)))]


class Listener(threading.Thread):
    def __init__(self, sim: SimService) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port, tcp_tune=True)
        self.frames: list[tuple[float, int, bytes]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.1)
            if msg is not None:
                self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.bus.shutdown()


def run_stack(n_drives: int, sync_ms: float, seconds: float, command_hz: float) -> dict[str, Any]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float32

    from nodes.qos import COMMAND_QOS, DIAGNOSTICS_QOS

    with SimService([SimDriveSpec(i) for i in range(1, n_drives + 1)], port=0) as sim, \
            tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "bench.yaml"
        drives = "".join(f"  - {{name: j{i}, node_id: {i}, counts_per_rev: 4096, max_velocity_deg_s: 3600,"
                         f" profile_velocity_deg_s: 3600, profile_acceleration_deg_s2: 100000}}\n"
                         for i in range(1, n_drives + 1))
        config.write_text(f"buses:\n  - {{name: can0, interface: socketcand, channel: can0, sync_period_ms: {sync_ms},"
                          f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}\ndrives:\n{drives}")
        proc = subprocess.Popen([sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p", f"config:={config}",
                                 "-p", "arm:=true", "-p", "state_rate_hz:=50.0", "-p", "diagnostics_rate_hz:=2.0"],
                                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        listener = Listener(sim)
        listener.start()
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_publisher", context=context)
        diags: list[Any] = []
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, DIAGNOSTICS_QOS)
        pubs = [node.create_publisher(Float32, f"j{i}/degree_cmd", COMMAND_QOS) for i in range(1, n_drives + 1)]
        from rclpy.executors import SingleThreadedExecutor
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            deadline = time.monotonic() + 30
            sims = [sim.simulator_for(i) for i in range(1, n_drives + 1)]
            while not all(s.call(lambda s=s, i=i: s.drive(i).state.name) == "OPERATION_ENABLED"
                          for i, s in enumerate(sims, start=1)):
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("the measured process did not enable its drives")
                time.sleep(0.1)
            while node.count_subscribers(f"j{n_drives}/degree_cmd") == 0:
                time.sleep(0.05)
            time.sleep(0.5)
            sent: dict[tuple[int, int], list[float]] = {}
            cpu0, wall0 = proc_cpu_s(proc.pid), time.monotonic()
            window0 = time.time()
            period = 1.0 / command_hz
            next_t = time.monotonic()
            k = 0
            while time.monotonic() - wall0 < seconds:
                k += 1
                angle = (k % 3000) * 0.1 + 0.05
                for i, pub in enumerate(pubs, start=1):
                    sent.setdefault((i, round(angle * COUNTS_PER_DEG) % 4096), []).append(time.time())
                    pub.publish(Float32(data=angle))
                executor.spin_once(timeout_sec=0)
                next_t += period
                time.sleep(max(0.0, next_t - time.monotonic()))
            cpu = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
            window1 = time.time()
            rss = proc_rss_peak_mb(proc.pid)
            for i, s in enumerate(sims, start=1):  # the drives stop sending: loss can be counted exactly
                s.call(lambda s=s, i=i: setattr(s.drive(i), "nmt", 0x7F))
            time.sleep(0.3)
            sim_tpdos = sum(s.call(lambda s=s, i=i: s.drive(i).counters["tpdo"]) for i, s in enumerate(sims, start=1))
            diags.clear()
            end = time.monotonic() + 3
            while time.monotonic() < end and not diags:
                executor.spin_once(timeout_sec=0.1)
            applied = sum(int(kv.value) for st in diags[-1].status for kv in st.values if kv.key == "tpdos_applied")
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown(context=context)
            proc.terminate()
            proc.wait(20)
            listener.close()
    latencies = []
    matched = 0
    for t, cob, data in listener.frames:
        if 0x301 <= cob <= 0x300 + n_drives and len(data) >= 6 and data[0] & 0x10:
            # continuous joints go the short way: the target on the wire is multi-turn, so match
            # it modulo one revolution (4096 counts)
            times = sent.get((cob - 0x300, int.from_bytes(data[2:6], "little", signed=True) % 4096), [])
            while times and times[0] < t - 1.0:
                times.pop(0)  # a command superseded before it was sent (latest wins), 30 s ago
            if times and times[0] <= t:
                latencies.append((t - times.pop(0)) * 1000)
                matched += 1
    unmatched = sum(len(v) for v in sent.values())
    syncs = [t for t, cob, _ in listener.frames if cob == 0x080]
    periods = [(b - a) * 1e6 for a, b in itertools.pairwise(syncs)]
    jitter = [abs(p - sync_ms * 1000) for p in periods]
    # the driver's heartbeat (node 127) as the drives see it: its longest gap is what their
    # consumer time (150 ms by default) must cover while the process is busy
    beats = [t for t, cob, _ in listener.frames if cob == 0x77F and window0 <= t <= window1]
    gaps = [(b - a) * 1000 for a, b in itertools.pairwise(beats)]
    return {"host_heartbeat_gap_p99_ms": round(pct(gaps, 0.99), 1) if gaps else None,
            "host_heartbeat_gap_max_ms": round(max(gaps), 1) if gaps else None,
            "cmd_latency_p50_ms": round(statistics.median(latencies), 3) if latencies else None,
            "cmd_latency_p99_ms": round(pct(latencies, 0.99), 3) if latencies else None,
            "commands_matched": matched, "commands_superseded": unmatched,
            "tpdo_sent": sim_tpdos, "tpdo_applied": applied, "tpdo_loss": sim_tpdos - applied,
            "cpu_core_fraction": round(cpu, 3), "rss_mb": round(rss, 1),
            "sync_jitter_p99_us": round(pct(jitter, 0.99), 1) if jitter else None}


def bare_path(seconds: float) -> dict[str, Any]:
    """rclpy publish -> subscription callback -> one python-can send, to the listener.

    The subscriber is its own process (``bare_peer.py``), as the driver node is: publisher and
    subscriber in one process would take DDS's intra-process shortcut the node never gets.
    """
    import rclpy
    from std_msgs.msg import Float32

    from nodes.qos import COMMAND_QOS

    with SimService([], port=0) as sim:
        listener = Listener(sim)
        listener.start()
        peer = subprocess.Popen([sys.executable, str(Path(__file__).resolve().parent / "bare_peer.py"), sim.host,
                                 str(sim.port)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bare", context=context)
        pub = node.create_publisher(Float32, "bare_cmd", COMMAND_QOS)
        try:
            assert peer.stdout is not None and peer.stdout.readline().strip() == "ready"
            deadline = time.monotonic() + 10
            while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            sent: dict[int, float] = {}
            start = time.monotonic()
            k = 0
            while time.monotonic() - start < seconds:
                k += 1
                angle = (k % 3000) * 0.1 + 0.05
                sent[round(angle * COUNTS_PER_DEG)] = time.time()
                pub.publish(Float32(data=angle))
                time.sleep(0.01)
            time.sleep(0.3)
        finally:
            peer.terminate()
            peer.wait(10)
            node.destroy_node()
            rclpy.shutdown(context=context)
            listener.close()
    latencies = [(t - sent.pop(int.from_bytes(d[2:6], "little", signed=True))) * 1000
                 for t, cob, d in listener.frames if cob == 0x301 and int.from_bytes(d[2:6], "little", signed=True) in sent]
    return {"bare_latency_p50_ms": round(statistics.median(latencies), 3)}


def state_run(script: str, prefix: str, n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    """A driver-level state run (no ROS) in its own process: TPDO loss and CPU."""
    with SimService([SimDriveSpec(i) for i in range(1, n_drives + 1)], port=0) as sim:
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve().parent / script),
                                 sim.host, str(sim.port), str(n_drives), str(sync_ms), str(seconds)],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=REPO)
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("measuring")
        cpu0, wall0 = proc_cpu_s(proc.pid), time.monotonic()
        time.sleep(seconds)
        cpu = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
        sims = [sim.simulator_for(i) for i in range(1, n_drives + 1)]
        for i, s in enumerate(sims, start=1):
            s.call(lambda s=s, i=i: setattr(s.drive(i), "nmt", 0x7F))
        time.sleep(0.3)
        sent = sum(s.call(lambda s=s, i=i: s.drive(i).counters["tpdo"]) for i, s in enumerate(sims, start=1))
        proc.stdin = None
        out = json.loads(proc.stdout.readline())
        proc.wait(30)
    return {f"{prefix}_tpdo_loss": sent - out["received"], f"{prefix}_tpdo_sent": sent,
            f"{prefix}_cpu_core_fraction": round(cpu, 3)}


def baseline_canopen(n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    return state_run("baseline_canopen.py", "baseline_canopen", n_drives, sync_ms, seconds)


def driver_only(n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    return state_run("driver_only.py", "driver_only", n_drives, sync_ms, seconds)


if __name__ == "__main__":
    print(json.dumps({**run_stack(6, 10.0, 10.0, 100.0), **bare_path(5.0)}, indent=2))

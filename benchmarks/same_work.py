"""The canopen library doing the stack run's CAN work (``baseline_canopen_rover.py``), measured as
the stack run measures the driver node: the same simulator (``rovercan sim --config`` with the
drive models in processes of their own), the same config with only its port changed, CPU from
/proc over the same window, TPDO loss against an independent listener after the drives were
stopped by NMT. The reference of the issue's CPU ratio: "the canopen baseline, same work".

The same work includes its timing: the SYNC every period and each drive's set-point every
command period, on the wire. Opened without the config's transport settings (python-can's
``tcp_tune``, which the driver's buses have by default) the library's SYNCs and RPDOs left in
clumps every 40-50 ms (Nagle's algorithm waiting for delayed ACKs) and its receive threads read
five periods' TPDOs at once: a fifth of the wake-ups, not the same work. It now connects with
the config's own bus arguments, and a run whose SYNC or set-points did not keep their period on
the wire fails (:func:`cadence`)."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from stack_run import (
    REPO,
    Listener,
    on_port,
    pct,
    proc_cpu_s,
    python_thread_names,
    simulator,
    thread_cpu_s,
    tpdos_on_wire,
    unboosted,
)
from verdicts import InvalidBaseline

#: The longest gap, p99, between two SYNCs, or two set-points to one drive, on the wire, in
#: periods: the library's own cyclic thread and command loop run late by a few milliseconds on a
#: busy machine; clumped by Nagle's algorithm they came 4-5 periods apart.
CADENCE_MAX_PERIODS = 2.0


def cadence(frames: list[tuple[float, int, bytes]], cob_id: int, start: float, end: float) -> float:
    """The p99 gap (s) between consecutive frames ``cob_id`` stamped within [start, end] on the wire."""
    stamps = [t for t, cob, _ in frames if cob == cob_id and start <= t <= end]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    return pct(gaps, 0.99) if gaps else float("inf")


def baseline_same_work(config_path: Path, seconds: float, command_hz: float, priority: int = 0) -> dict[str, Any]:
    """``priority`` > 0: the baseline's threads under SCHED_FIFO, as the node's; the keys then say ``_rt``."""
    from can_config import load_config
    from can_config.objects import FunctionCode

    shipped = load_config(config_path)
    channels = sorted({b.channel for b in shipped.buses})
    prefix = "baseline_canopen_same_work" + ("_rt" if priority else "")
    with simulator("--config", str(config_path), "--drive-processes") as port, tempfile.TemporaryDirectory() as tmp, \
            tempfile.TemporaryFile("w+") as err:  # a pipe nobody reads could block it
        config = on_port(config_path, port, tmp)
        listeners = [Listener(port, ch) for ch in channels]
        for listener in listeners:
            listener.start()
        proc = subprocess.Popen(unboosted([sys.executable, str(Path(__file__).resolve().parent / "baseline_canopen_rover.py"),
                                 str(config), str(command_hz), str(seconds), str(priority)]),
                                cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True)
        try:
            assert proc.stdout is not None
            if not proc.stdout.readline().startswith("measuring"):
                proc.wait(30)
                err.seek(0)
                raise RuntimeError(f"the canopen baseline did not start: {err.read()[-2000:]}")
            names = python_thread_names(proc.pid)
            time.sleep(0.5)
            cpu0, wall0, threads0 = proc_cpu_s(proc.pid), time.monotonic(), thread_cpu_s(proc.pid, names)
            window0 = time.time()
            time.sleep(seconds - 0.5)
            window1 = time.time()
            wall = time.monotonic() - wall0
            cpu = (proc_cpu_s(proc.pid) - cpu0) / wall
            threads = {name: (t - threads0.get(name, 0.0)) / wall for name, t in thread_cpu_s(proc.pid, names).items()}
            t_stop = time.time()
            for listener in listeners:  # the drives stop sending: loss can be counted exactly
                listener.send(0x000, bytes([0x80, 0]))
            out = json.loads(proc.stdout.readline())
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            for listener in listeners:
                listener.close()
    # each drive's command rate (command_hz, or with 0 its bus's SYNC rate, as stack_run.command_rates)
    sync_by_bus = {b.name: b.sync_period_s for b in shipped.buses}
    drive_hz = {d.name: command_hz or 1.0 / sync_by_bus[d.bus] for d in shipped.drives}
    ramp_deg = 0.1 * min(drive_hz.values()) * seconds
    if not out["followed_deg"] > ramp_deg / 2:
        raise InvalidBaseline(f"the canopen baseline's drives did not follow its commands (moved {out['followed_deg']} deg of"
                           f" a {ramp_deg:.0f} deg ramp): it did not do the same work")
    sent = tpdos_on_wire(listeners, t_stop)
    # each bus's SYNC gap in its own periods (the rover's wheels every 10 ms beside an arm every 2 ms)
    sync_period = {b.channel: b.sync_period_s for b in shipped.buses}
    sync_gaps = {listener.channel: cadence(listener.frames, FunctionCode.SYNC, window0, window1) for listener in listeners}
    sync_gap = max(sync_gaps.values())
    sync_late = max(gap / sync_period[channel] for channel, gap in sync_gaps.items())
    by_channel = {listener.channel: listener.frames for listener in listeners}
    buses = {b.name: b.channel for b in shipped.buses}
    # each drive's set-point: RPDO2, as baseline_canopen_rover.py sends it
    # each drive's set-point gap in its own command periods
    command_gaps = {d.name: cadence(by_channel[buses[d.bus]], FunctionCode.RPDO2 + d.node_id, window0, window1)
                    for d in shipped.drives}
    command_gap = max(command_gaps.values())
    late = max(gap * drive_hz[name] / 1.001 for name, gap in command_gaps.items())
    if sync_late > CADENCE_MAX_PERIODS or late > CADENCE_MAX_PERIODS:
        raise InvalidBaseline(f"the canopen baseline's frames did not keep their period on the wire (p99 gap: SYNC"
                           f" {sync_gap * 1000:.1f} ms, {sync_late:.1f} of its periods; set-points"
                           f" {command_gap * 1000:.1f} ms, {late:.1f} of theirs): it did not do the same work")
    return {f"{prefix}_tpdo_sent": sent, f"{prefix}_sync_gap_p99_ms": round(sync_gap * 1000, 2),
            f"{prefix}_command_gap_p99_ms": round(command_gap * 1000, 2),
            f"{prefix}_tpdo_loss": sent - out["received"], f"{prefix}_followed_deg": out["followed_deg"],
            f"{prefix}_cpu_core_fraction": round(cpu, 3),
            f"{prefix}_cpu_by_thread": {name: round(f, 3) for name, f in sorted(threads.items(), key=lambda kv: -kv[1])
                                        if f >= 0.002}}


if __name__ == "__main__":
    from stack_run import SHIPPED

    rt = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    print(json.dumps(baseline_same_work(SHIPPED["rover"], 10.0, 100.0, rt), indent=1))

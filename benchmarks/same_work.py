"""The canopen library doing the stack run's CAN work (``baseline_canopen_rover.py``), measured as
the stack run measures the driver node: the same simulator (``rovercan sim --config`` with the
drive models in processes of their own), the same config with only its port changed, CPU from
/proc over the same window, TPDO loss against an independent listener after the drives were
stopped by NMT. The reference of the issue's CPU ratio: "the canopen baseline, same work"."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from stack_run import REPO, Listener, on_port, proc_cpu_s, python_thread_names, simulator, thread_cpu_s, tpdos_on_wire


def baseline_same_work(config_path: Path, seconds: float, command_hz: float, priority: int = 0) -> dict[str, Any]:
    """``priority`` > 0: the baseline's threads under SCHED_FIFO, as the node's; the keys then say ``_rt``."""
    from can_config import load_config

    channels = sorted({b.channel for b in load_config(config_path).buses})
    prefix = "baseline_canopen_same_work" + ("_rt" if priority else "")
    with simulator("--config", str(config_path), "--drive-processes") as port, tempfile.TemporaryDirectory() as tmp, \
            tempfile.TemporaryFile("w+") as err:  # a pipe nobody reads could block it
        config = on_port(config_path, port, tmp)
        listeners = [Listener(port, ch) for ch in channels]
        for listener in listeners:
            listener.start()
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve().parent / "baseline_canopen_rover.py"),
                                 str(config), str(command_hz), str(seconds), str(priority)],
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
            time.sleep(seconds - 0.5)
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
    ramp_deg = 0.1 * command_hz * seconds
    if not out["followed_deg"] > ramp_deg / 2:
        raise RuntimeError(f"the canopen baseline's drives did not follow its commands (moved {out['followed_deg']} deg of"
                           f" a {ramp_deg:.0f} deg ramp): it did not do the same work")
    sent = tpdos_on_wire(listeners, t_stop)
    return {f"{prefix}_tpdo_sent": sent, f"{prefix}_tpdo_loss": sent - out["received"], f"{prefix}_followed_deg": out["followed_deg"],
            f"{prefix}_cpu_core_fraction": round(cpu, 3),
            f"{prefix}_cpu_by_thread": {name: round(f, 3) for name, f in sorted(threads.items(), key=lambda kv: -kv[1])
                                        if f >= 0.002}}


if __name__ == "__main__":
    from stack_run import SHIPPED

    rt = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    print(json.dumps(baseline_same_work(SHIPPED["rover"], 10.0, 100.0, rt), indent=1))

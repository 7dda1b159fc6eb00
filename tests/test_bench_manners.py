"""What a user meets first on the bench: Ctrl-C at any moment gives one line, `enable` says what
happens as it exits, a step test works on a continuous joint that has turned a few times."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import REPO, rovercan_cli, rovercan_sim

GENERIC_EDS_ARG = "generic"


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return rovercan_cli(*args)


def bus(port: int) -> list[str]:
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={port}"]


@pytest.mark.parametrize("after_start_s", [0.0, 0.03, 0.08, 0.15, 0.25, 0.4, 0.7])
def test_ctrl_c_at_any_moment_gives_one_line_and_no_traceback(after_start_s: float) -> None:
    """From the moment rovercan's own code can run (its entry module imported: Python reports
    each import as it completes with PYTHONPROFILEIMPORTTIME; a Ctrl-C before that is Python's
    own, 'Fatal Python error: init_import_site'), then ``after_start_s`` on: while it imports
    python-can, canopen and the rest (about 0.3 s), while it opens the bus, while it works."""
    script = Path(sys.executable).parent / "rovercan"  # the console script users run
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "rovercan"]
    proc = subprocess.Popen([*argv, "monitor", "-i", "virtual", "-c", "rovercan-ctrl-c", "--seconds", "5"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPROFILEIMPORTTIME": "1"})
    assert proc.stderr is not None
    early = []
    for line in proc.stderr:  # ends at the process's end: a hang is the subprocess timeout below
        early.append(line)
        if line.rstrip().endswith("| rovercan.entry"):
            break
    assert early and early[-1].rstrip().endswith("| rovercan.entry"), "".join(early[-20:])
    time.sleep(after_start_s)  # the moment of the Ctrl-C, counted from there (not a wait)
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=60)
    err = "".join(line for line in [*early, *rest.splitlines(keepends=True)] if not line.startswith("import time:"))
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert proc.returncode != 0 or "frames" in err, (proc.returncode, err)  # stopped, or done by then


def test_a_ctrl_c_inside_an_interpreter_callback_still_ends_the_process() -> None:
    """The Ctrl-C handled while the interpreter runs a callback of its own (an import lock's
    weakref callback, where a fresh clone's run caught it): an exception raised there is printed
    as "Exception ignored" and the program runs on, so the early handler ends the process itself."""
    script = ("import os, signal, weakref\n"
              "import rovercan.entry\n"
              "class Lock: pass\n"
              "lock = Lock()\n"
              "ref = weakref.ref(lock, lambda _: os.kill(os.getpid(), signal.SIGINT))\n"
              "del lock\n"
              "print('ran on after the Ctrl-C', flush=True)\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130 and "ran on" not in proc.stdout, (proc.returncode, proc.stdout, proc.stderr)
    assert proc.stderr == "rovercan: interrupted (Ctrl-C)\n", proc.stderr


def test_a_stop_signal_inside_an_interpreter_callback_still_leaves_the_block() -> None:
    """stop_on_signals (every bench command's): the stop raised while the interpreter runs a
    callback of its own was printed as "Exception ignored" and lost, the block ran on and every
    later Ctrl-C was ignored (the first had been taken): it reaches the block now."""
    script = ("import os, signal, time, weakref\n"
              "from motor_driver.process.stop import stop_on_signals\n"
              "class Lock: pass\n"
              "with stop_on_signals() as stop:\n"
              "    lock = Lock()\n"
              "    ref = weakref.ref(lock, lambda _: os.kill(os.getpid(), signal.SIGINT))\n"
              "    del lock\n"
              "    for _ in range(3000):\n"
              "        time.sleep(0.01)\n"
              "    print('ran on', flush=True)\n"
              "print('left on', signal.Signals(stop.signum).name, flush=True)\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout == "left on SIGINT\n", (proc.stdout, proc.stderr)
    assert "Exception ignored" not in proc.stderr, proc.stderr


def test_enable_says_the_drive_is_disabled_again_as_it_exits() -> None:
    with rovercan_sim() as port:
        result = run("enable", "1", "--eds", GENERIC_EDS_ARG, *bus(port), "--json")
        assert result.returncode == 0, result.stderr
        assert "disabled again as the command exits; --hold S" in json.loads(result.stdout)["on_exit"]
        held = run("enable", "1", "--eds", GENERIC_EDS_ARG, *bus(port), "--json", "--hold", "0.2")
        assert json.loads(held.stdout)["on_exit"] == "held enabled 0.2 s, then disabled"


def test_a_step_test_on_a_continuous_joint_after_a_few_turns(tmp_path: Path) -> None:
    with rovercan_sim() as port:
        jogged = run("jog", "1", "350", "--for", "2.5", *bus(port), "--json")  # about two turns
        assert jogged.returncode == 0, jogged.stderr
        assert json.loads(jogged.stdout)["angle_deg"] > 400.0
        stepped = run("step-test", "1", "--step", "20", "--seconds", "1.5", "--out", str(tmp_path / "s"), *bus(port))
        assert stepped.returncode == 0, stepped.stderr
        metrics = json.loads((tmp_path / "s.json").read_text())
        assert metrics["start_deg"] > 400.0 and metrics["steady_state_error_deg"] < 0.3, metrics

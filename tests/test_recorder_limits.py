"""A driver on a bad day stays readable (issue 41): an incident directory that cannot be written
is one WARNING and the incidents stay in memory; the same incident again and again is counted,
not rewritten; no plot process starts while the process is starved; a repeated warning is one
line per period with a count. Times are given to the code (event times, an injected clock):
no test here reads a clock."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from can_config import config_to_dict, with_bus_overrides
from can_config.config import RecorderConfig
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.recording import flight
from motor_driver.recording.flight import REPEAT_WINDOW_S, FlightRecorder
from virtual_can import SimService

from .conftest import REPO, make_config, wait_for
from .test_mcap_incident import state

HANG_S = 30.0  # catches a hang only


def recorder(directory: Path, **config: object) -> FlightRecorder:
    cfg = RecorderConfig(dir=directory, seconds=5.0, after_s=0.0, **config)  # type: ignore[arg-type]
    return FlightRecorder(cfg, {"wheel": ("can0", 1), "other": ("can0", 2)}, {"can0": "can0"})


def test_an_unwritable_directory_is_one_warning_and_the_incidents_are_kept(tmp_path: Path,
                                                                            caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    rec = recorder(blocker / "incidents", plot=False)  # a path under a file: no one can create it, not even root
    caplog.set_level(logging.DEBUG, logger="motor_driver.recording.flight")
    try:
        for i, kind in enumerate(("emcy", "heartbeat_lost", "watchdog_stop")):
            rec.trigger(kind, "can0", node=1, t=1000.0 + i)
            wait_for(lambda n=i: len(rec.kept) == n + 1, HANG_S, f"incident {i} kept")
    finally:
        rec.close()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "cannot write incidents to" in warnings[0].getMessage() and "kept in memory" in warnings[0].getMessage()
    assert not any(r.exc_info for r in caplog.records)  # no traceback
    assert [k["kind"] for k in rec.kept] == ["emcy", "heartbeat_lost", "watchdog_stop"]
    assert rec.written == []


def test_the_same_incident_again_is_counted_in_the_next_one_written(tmp_path: Path) -> None:
    rec = recorder(tmp_path, plot=False)
    t0 = 1_000_000.0
    try:
        rec.trigger("heartbeat_lost", "can0", node=1, t=t0)
        wait_for(lambda: len(rec.written) == 1, HANG_S, "the first incident written")
        for i in range(1, 6):  # the drive flaps: five more within the window
            rec.trigger("heartbeat_lost", "can0", node=1, t=t0 + i)
        rec.trigger("heartbeat_lost", "can0", node=2, t=t0 + 7)  # another drive: its own incident
        rec.trigger("heartbeat_lost", "can0", node=1, t=t0 + REPEAT_WINDOW_S + 1)  # after the window
        wait_for(lambda: len(rec.written) == 3, HANG_S, "two more incidents written")
    finally:
        rec.close()
    import json

    summaries = [json.loads(p.read_text()) for p in rec.written]
    assert [(s["events"][0]["drive"], s["repeats"]) for s in summaries] == [("wheel", 0), ("other", 0), ("wheel", 5)]


def test_no_plot_process_while_the_process_is_late_and_the_plot_drawn_when_it_stops(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Starved, the recorder starts no plot process beside the driver; the plot is not lost for it
    (11 of 24 incidents had none): the summary names it and the reason it waits, and it is drawn
    when the driver stops (or once the process is on time again)."""
    import json

    # the plot is what is checked here, not close()'s budget for it (tests/test_recorder_helpers.py):
    # a crowded machine draws a low-priority plot slower than the budget
    monkeypatch.setattr(flight, "PLOT_WAIT_S", 120.0)
    rec = recorder(tmp_path, plot=True)
    try:
        rec.sample([state("wheel", 0.0)])  # a state sample: an incident with states is plotted
        rec.process_late()
        rec.trigger("emcy", "can0", node=1, t=2_000_000.0)
        wait_for(lambda: len(rec.written) == 1, HANG_S, "the incident written")
        summary = json.loads(rec.written[0].read_text())
        assert summary["png"] and "went out late" in summary["plot_deferred"]
        assert not list(tmp_path.glob("*.png"))
    finally:
        rec.close()
    png = tmp_path / summary["png"]
    wait_for(lambda: png.exists() and png.stat().st_size > 1000, HANG_S, "the deferred plot drawn at close")


def test_a_repeated_warning_is_one_line_per_period_with_a_count(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    log = RateLimitedLog(logging.getLogger("test.ratelimit"), period_s=10.0, clock=lambda: now[0])
    caplog.set_level(logging.WARNING, logger="test.ratelimit")
    logged = []
    for step in range(100):  # 100 lines over 9.9 s, then one at 10 s
        now[0] = step * 0.1
        logged.append(log.log(logging.WARNING, "late", "late by %d ms", step))
    now[0] = 10.0
    assert log.log(logging.WARNING, "late", "late by %d ms", 100)
    assert log.log(logging.WARNING, "other", "another kind")  # each kind its own
    assert logged.count(True) == 1 and logged[0]
    assert [r.getMessage() for r in caplog.records] == [
        "late by 0 ms", "late by 100 ms (99 more like this in the last 10 s)", "another kind"]


DRIVER = """
import sys
from can_config import load_config
from motor_driver.process.stop import StopSignal
from motor_driver import MotorDriver
with StopSignal() as stop, MotorDriver(load_config(sys.argv[1])) as driver:
    driver.start()
    print("started", flush=True)
    stop.event.wait()
"""


def test_a_starved_driver_says_so_once_not_once_a_beat(tmp_path: Path) -> None:
    """The driver's process stopped (SIGSTOP) and resumed eight times: each time its host heartbeat
    goes out late. The late warning is said once (then counted), not eight times."""
    config = make_config(1, host_timeout_ms=5000.0)
    with SimService.from_config(config, port=0) as sim:
        import yaml

        path = tmp_path / "one.yaml"
        path.write_text(yaml.safe_dump(config_to_dict(with_bus_overrides(config, host=sim.host, port=sim.port))))
        proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(path)], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
            for _ in range(8):  # each stop is six heartbeat periods and more: every resume is a late beat
                proc.send_signal(signal.SIGSTOP)
                time.sleep(0.3)
                proc.send_signal(signal.SIGCONT)
                time.sleep(0.3)
        finally:
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=HANG_S)
    late = [line for line in err.splitlines() if "host heartbeat" in line and "late" in line]
    assert 1 <= len(late) <= 2, err[-3000:]  # without the rate limit: eight or more
    assert "Traceback" not in err

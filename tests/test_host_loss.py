"""Drive-side safety: the drives stop by themselves when the driver's process dies or hangs.

The driver runs in a process of its own (tests/clients/hold_velocity.py) and is killed with
SIGKILL or frozen with SIGSTOP: no handler of ours runs. Independent clients on the bus (a
python-can listener and a canopen SDO client of the test's own) show every drive leaving
Operation Enabled within the consumer time + 100 ms and standing still.

The ROS processes (the lifecycle node, the driver following a trajectory: their tests are in
test_lifecycle.py and test_follow_trajectory.py) are killed or frozen as they move, and judged by
``signal_the_host_and_see_the_drives_stop``: each drive's EMCY 0x8130 and nothing of the host after
it, then the drive disabled and still, read by SDO; outcomes and order, no clock.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
import pytest

from can_config import RoverConfig, load_config, load_drive_od, parse_config
from can_config.config import GENERIC_EDS
from can_config.errors import CommandRejected, DriveTimeoutError
from motor_driver import MotorDriver, State
from motor_driver.protocol.pdo import plan_pdos
from virtual_can import SimDriveSpec, SimService, VirtualBus
from virtual_can.server import RAWMODE_HOLD_S

from .conftest import MARKER_COB, REPO, SHARED_EDS, enable_letting_go, make_config, requires_shared, wait_for

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]
CLIENT = REPO / "tests" / "clients" / "hold_velocity.py"
MARKERS = itertools.count(1)
HOST_TIMEOUT_S = 0.15  # the default: 3 x the 50 ms host heartbeat
BOUND_S = HOST_TIMEOUT_S + 0.1


def statusword_enabled(sw: int) -> bool:
    return sw & 0x6F == 0x27


@dataclass
class Watch:
    """Frames of one channel with their bus time (the server stamps each frame as it enters the
    bus, wall clock), collected by a thread of the test's own."""

    bus: can.BusABC
    frames: list[tuple[float, can.Message]] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append((msg.timestamp, msg))


@contextmanager
def watching(sim: SimService, channels: list[str]) -> Iterator[dict[str, Watch]]:
    watches = {ch: Watch(can.Bus(interface="socketcand", channel=ch, host=sim.host, port=sim.port)) for ch in channels}
    threads = [threading.Thread(target=w.run, daemon=True) for w in watches.values()]
    for thread in threads:
        thread.start()
    time.sleep(RAWMODE_HOLD_S + 0.05)
    try:
        yield watches
    finally:
        for w in watches.values():
            w.stop.set()
        for thread in threads:
            thread.join()
        for w in watches.values():
            w.bus.shutdown()


def write_config(path: Path, port: int, drives: list[tuple[str, int, str, Path]], **extra: object) -> Path:
    """drives: (name, node id, channel, eds)."""
    channels = sorted({ch for _, _, ch, _ in drives})
    lines = ["buses:"]
    lines += [f"  - {{name: {ch}, interface: socketcand, channel: {ch}, kwargs: {{host: 127.0.0.1, port: {port}}}}}"
              for ch in channels]
    lines.append("drives:")
    keys = {"counts_per_rev": 4096, "gear_ratio": 10, "max_velocity_deg_s": 720, "profile_acceleration_deg_s2": 2000,
            **extra}
    more = "".join(f", {k}: {v}" for k, v in keys.items())
    lines += [f"  - {{name: {name}, node_id: {node}, bus: {ch}, eds: '{eds}'{more}}}" for name, node, ch, eds in drives]
    path.write_text("\n".join(lines) + "\n")
    return path


def put_marker(sim: SimService, channel: str) -> bytes:
    """A marker frame of a token of its own on ``channel``, from the bus itself; the token."""
    token = next(MARKERS).to_bytes(4, "little")
    with VirtualBus(channel, engine=sim.engine) as marker:
        marker.send(can.Message(arbitration_id=MARKER_COB, data=token, is_extended_id=False))
    return token


def syncs_while_listening(sim: SimService, watch: Watch, channel: str, node: int) -> int:
    """SYNCs ``watch`` heard between a marker put on ``channel`` now and the second heartbeat of
    ``node`` after it (a span of at least one heartbeat period, many SYNC periods): 0 says no SYNC
    came while the watch was shown to listen."""
    token = put_marker(sim, channel)

    def since_marker() -> list[can.Message]:
        frames = [m for _, m in list(watch.frames)]
        at = next((i for i, m in enumerate(frames) if m.arbitration_id == MARKER_COB and bytes(m.data) == token), None)
        return [] if at is None else frames[at + 1:]

    def beats() -> list[int]:
        return [i for i, m in enumerate(since_marker()) if m.arbitration_id == 0x700 + node]

    wait_for(lambda: len(beats()) >= 2, 30.0, f"two heartbeats of node {node} after the marker on {channel}")
    return sum(m.arbitration_id == 0x080 for m in since_marker()[:beats()[1]])


def first_stop(frames: list[tuple[float, can.Message]], cob_id: int, offset: int, after: float) -> float | None:
    """Arrival time of the first frame after ``after`` by which the drive says it stopped itself:
    a statusword (in TPDO ``cob_id`` at byte ``offset``) no longer in Operation Enabled, or its
    EMCY 0x8130 (host heartbeat lost: its 0x6007 reaction comes with it; a drive whose 0x1029 takes
    it to PRE-OPERATIONAL on that error sends no TPDO after it). The tests read its state by SDO
    after."""
    emcy = 0x080 + (cob_id & 0x7F)
    for t, msg in frames:
        if t < after:
            continue
        if msg.arbitration_id == cob_id and len(msg.data) >= offset + 2 \
                and not statusword_enabled(int.from_bytes(msg.data[offset:offset + 2], "little")):
            return t
        if msg.arbitration_id == emcy and bytes(msg.data[:2]) == b"\x30\x81":
            return t
    return None


def statusword_tpdo(eds: Path, node: int) -> tuple[int, int]:
    """COB-ID and byte offset of the first event-driven TPDO carrying the statusword, as the driver maps it."""
    for pdo in plan_pdos(load_drive_od(eds, node), node).tpdos:
        offset = 0
        for index, _, dtype in pdo.objects:
            if index == 0x6041 and pdo.trans_type >= 254:
                return pdo.cob_id, offset
            offset += {0x2: 1, 0x5: 1, 0x3: 2, 0x6: 2}.get(dtype, 4)
    raise AssertionError(f"{eds.name}: no event-driven statusword TPDO")


def signal_and_wait(proc: subprocess.Popen[str], sig: int, sim: SimService, watches: dict[str, Watch]
                    ) -> tuple[float, str, str]:
    """Send ``sig``, wait for the process to end (killed after 10 s); the signal's wall time,
    then stdout and stderr. Once the server has closed the process's connections (every frame
    it sent is on the bus), a marker put on each bus after them reaches each watch: the watches
    hold the process's last frames."""
    t_signal = time.time()
    proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    watches_heard_all(sim, watches, len(watches))
    return t_signal, out, err


def watches_heard_all(sim: SimService, watches: dict[str, Watch], clients: int) -> None:
    """Once the server is down to ``clients`` connections (a process that ended: every frame it
    sent is on the bus), put a marker on each bus and wait until its watch heard it: the watch
    holds every frame the bus carried before."""
    wait_for(lambda: len(sim.server.clients) == clients, 10.0, f"the server down to {clients} connections")
    for channel, watch in watches.items():
        token = put_marker(sim, channel)
        wait_for(lambda w=watch, t=token: any(m.arbitration_id == MARKER_COB and bytes(m.data) == t  # type: ignore[misc]
                                              for _, m in list(w.frames)), 10.0, f"the marker at {channel}'s watch")


def run_and_stop(tmp_path: Path, drives: list[tuple[str, int, str, Path]], sig: int, velocity: float = 60.0,
                 **extra: object) -> None:
    specs = [SimDriveSpec(node, eds, ch, name, 4096) for name, node, ch, eds in drives]
    with SimService(specs, port=0) as sim:
        config = write_config(tmp_path / "rover.yaml", sim.port, drives, **extra)
        channels = sorted({ch for _, _, ch, _ in drives})
        with watching(sim, channels) as watches:
            proc = subprocess.Popen([sys.executable, str(CLIENT), str(config), str(velocity)], cwd=REPO,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            try:
                assert proc.stdout is not None
                line = proc.stdout.readline()
                assert line.strip() == "READY", (line, proc.stderr.read() if proc.poll() is not None else "")
                for name, node, ch, _ in drives:
                    sim_drive = sim.simulators[ch].drive(node)
                    assert sim.simulators[ch].call(lambda d=sim_drive: d.state.name) == "OPERATION_ENABLED", name
                t_signal = time.time()
                proc.send_signal(sig)
                time.sleep(BOUND_S + 0.3)
                results = {}
                for name, node, ch, eds in drives:
                    cob, offset = statusword_tpdo(eds, node)
                    stopped = first_stop(watches[ch].frames, cob, offset, t_signal)
                    results[name] = None if stopped is None else stopped - t_signal
                heard = {ch: [t for t, m in w.frames if m.arbitration_id == 0x77F] for ch, w in watches.items()}
                syncs = {ch: [t for t, m in w.frames if m.arbitration_id == 0x080] for ch, w in watches.items()}
            finally:
                if sig == signal.SIGSTOP:
                    proc.kill()
                    proc.send_signal(signal.SIGCONT)
                proc.kill()
                proc.wait(10)
                if proc.stdout:
                    proc.stdout.close()
                if proc.stderr:
                    proc.stderr.close()
            # the SYNC comes from the bus daemon's timer: its job ends with a killed process's
            # connection (when the server sees it closed: a loaded machine takes its time); a hung
            # process keeps the connection, and the SYNC goes on (as with a kernel timer): the
            # drives stop on the missing heartbeat all the same
            if sig != signal.SIGSTOP:
                wait_for(lambda: len(sim.server.clients) == len(watches), 30.0, "the killed process's connection closed")
                for ch, watch in watches.items():
                    node = next(node for _, node, c, _ in drives if c == ch)
                    assert syncs_while_listening(sim, watch, ch, node) == 0, f"{ch}: SYNC after the connection closed"
        for ch, beats in heard.items():  # the host heartbeat was on each bus, and stopped with the process
            assert beats and beats[-1] < t_signal + 0.1, (ch, [round(t - t_signal, 3) for t in beats[-3:]])
            if sig == signal.SIGSTOP:
                assert [t for t in syncs[ch] if t > t_signal + 0.1], f"{ch}: no SYNC while the process was held"
        print(f"stop after {signal.Signals(sig).name}: " + ", ".join(f"{n} {dt * 1000:.0f} ms" if dt else f"{n} -"
                                                              for n, dt in results.items()))
        late = {name: dt for name, dt in results.items() if dt is None or dt > BOUND_S}
        assert not late, f"not stopped within {BOUND_S * 1000:.0f} ms of the signal: {late}"
        # an independent SDO client: every drive stands still and is not enabled
        for ch in channels:
            network = canopen.Network()
            network.connect(interface="socketcand", channel=ch, host=sim.host, port=sim.port)
            try:
                time.sleep(RAWMODE_HOLD_S + 0.02)
                for name, node, chan, eds in drives:
                    if chan != ch:
                        continue
                    remote = network.add_node(node, load_drive_od(eds, node))
                    sw = int.from_bytes(remote.sdo.upload(0x6041, 0), "little")
                    velocity_actual = int.from_bytes(remote.sdo.upload(0x606C, 0), "little", signed=True)
                    assert not statusword_enabled(sw) and velocity_actual == 0, (name, hex(sw), velocity_actual)
            finally:
                network.disconnect()


ROVER = [(f"wheel{i}", (i - 1) % 3 + 1, "can0" if i <= 3 else "can1", GENERIC_EDS) for i in range(1, 7)]


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "hung"])
def test_six_drives_on_two_buses_stop_when_the_driver_dies(tmp_path: Path, sig: int) -> None:
    run_and_stop(tmp_path, ROVER, sig)


def test_on_host_loss_fault_puts_the_drives_in_fault(tmp_path: Path) -> None:
    run_and_stop(tmp_path, ROVER[:2], signal.SIGKILL, on_host_loss="fault")


def can_watch_host(eds: Path) -> bool:
    """The EDS has a 0x1016:1 whose range holds a node id (Elmo's says HighLimit 65535: time only)."""
    od = load_drive_od(eds, 1)
    if 0x1016 not in od:
        return False
    high = od[0x1016][1].max
    return high is None or high >= 127 << 16 | 150


VENDOR = [p for p in sorted(SHARED_EDS.glob("*.eds")) if p.name != "python_canopen_sample.eds"] \
    if SHARED_EDS.is_dir() else []
WATCHING_EDS = [p for p in VENDOR if can_watch_host(p)]
BLIND_EDS = [p for p in VENDOR if not can_watch_host(p)]


@requires_shared
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "hung"])
def test_vendor_drives_with_a_consumer_heartbeat_stop_when_the_driver_dies(tmp_path: Path, sig: int) -> None:
    assert len(WATCHING_EDS) >= 5, [p.name for p in WATCHING_EDS]
    drives = [(p.stem.split("_")[0] + str(i), i, "can0", p) for i, p in enumerate(WATCHING_EDS, start=1)]
    run_and_stop(tmp_path, drives, sig, velocity=30.0, gear_ratio=1, max_velocity_deg_s=360,
                 profile_acceleration_deg_s2=360)


@requires_shared
@pytest.mark.parametrize("eds", BLIND_EDS, ids=lambda p: p.name)
def test_a_drive_that_cannot_watch_the_host_is_not_armed_unless_allowed(eds: Path, sim_factory: SimFactory) -> None:
    _, cfg = sim_factory(make_config(1, eds=str(eds), host_timeout_ms=150))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        assert drive.watch.host_watch is None
        text = eds.read_text(errors="replace")
        reason = ("refuses 0x1016:1 = 0x007F0096" if "1016" in text else
                  "node guarding needs remote frames" if "[100C]" in text else "has no consumer heartbeat")
        with pytest.raises(CommandRejected, match=f"enable refused: no drive-side stop on host loss: .*{reason}"):
            drive.enable()
        assert drive.cache.state is not State.OPERATION_ENABLED
    _, cfg = sim_factory(make_config(1, eds=str(eds), allow_no_host_watch=True, host_timeout_ms=150))
    with MotorDriver(cfg).start() as driver:
        driver.drive("joint1").enable()
        assert driver.drive("joint1").cache.state is State.OPERATION_ENABLED


def test_boot_writes_the_host_watch_and_close_releases_it(sim_factory: SimFactory) -> None:
    sim, cfg = sim_factory(make_config(1, host_timeout_ms=200, on_host_loss="disable"))
    sim_drive = sim.simulators["can0"].drive(1)

    def read(index: int, sub: int = 0) -> object:
        return sim.simulators["can0"].call(lambda: sim_drive.store.get(index, sub))

    driver = MotorDriver(cfg).start()
    try:
        assert read(0x1016, 1) == 127 << 16 | 200  # node 127, 200 ms
        assert read(0x6007) == 2 and read(0x605A) == 2
        wait_for(lambda: bool(sim.simulators["can0"].call(lambda: dict(sim_drive._consumer_seen))), 1.0,
                 "consumer armed by the host heartbeat")
    finally:
        driver.close()
    assert read(0x1016, 1) == 0  # a clean close leaves no armed watch behind: no EMCY after exit


def test_boot_sets_the_quick_stop_to_end_disabled_whatever_the_drive_defaults_to(tmp_path: Path,
                                                                                   sim_factory: SimFactory) -> None:
    """A drive whose own default is to stay in Quick Stop Active (0x605A = 6, maxon's EPOS4) is told
    2 at boot, as one whose default is 2 already: a host-loss quick stop then ends disabled."""
    od = canopen.import_od(str(GENERIC_EDS), 1)
    od[0x605A].default, od[0x605A].default_raw = 6, "6"
    eds = tmp_path / "quick_stop_6.eds"
    canopen.export_od(od, str(eds), doc_type="eds")
    sim, cfg = sim_factory(make_config(1, eds=str(eds)))
    sim_drive = sim.simulators["can0"].drive(1)
    assert sim.simulators["can0"].call(lambda: sim_drive.store.get(0x605A, 0)) == 6
    with MotorDriver(cfg).start():
        assert sim.simulators["can0"].call(lambda: sim_drive.store.get(0x605A, 0)) == 2


def test_enable_waits_until_the_drive_watches_the_host(driver_factory: Callable[[RoverConfig], tuple[SimService,
                                                                                                    MotorDriver]],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """CiA 301: a heartbeat consumer starts at the first heartbeat it hears after its entry is
    written. An enable before that (the lifecycle node's autostart enables right after the boot)
    armed a drive that nothing stopped if the process died then (test_stall[lifecycle]: SIGSTOP
    there left a drive Operation Enabled). The supervisor's host heartbeats are held back (sent
    by nobody, as by a starved loop) across a new boot: enable is refused and nothing sent; held
    until the enable waits for them, then let go: it returns with the drive watching."""
    sim, driver = driver_factory(make_config(1))
    drive, handle = driver.drive("joint1"), driver.buses["can0"]
    runner = sim.simulators["can0"]
    # heartbeats went out before the new boot: its count starts from theirs, not from zero
    wait_for(lambda: handle.beats_sent() >= 3, 30.0, "three host heartbeats sent")
    send_beat, held = handle.beat, threading.Event()
    held.set()
    monkeypatch.setattr(handle, "beat", lambda host: None if held.is_set() else send_beat(host))

    def sim_watching() -> bool:
        return bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen)))

    drive.boot.boot()  # told to watch the host again: a consumer that waits for its first heartbeat
    with pytest.raises(DriveTimeoutError, match=r"enable refused: the drive is not watching the host after 1 s: 0 of"
                                                r" the 2 host heartbeats \(node 127, every 50 ms\) it needs") as refused:
        drive.enable()
    assert refused.value.node_id == 1
    assert runner.call(lambda: runner.drive(1).state) != State.OPERATION_ENABLED and not sim_watching()
    enable_letting_go(drive, held)
    # the enable's own frames went after the heartbeats, and the drive answered them: it heard those
    assert sim_watching() and drive.cache.state is State.OPERATION_ENABLED


def test_two_host_heartbeats_after_a_boot_let_a_drive_be_enabled_and_it_then_watches(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]], monkeypatch: pytest.MonkeyPatch) -> None:
    """The wait is for two heartbeats sent since the boot, not more: with the supervisor's held
    back, two sent by hand while the enable waits let it through. The host then stays silent,
    and the drive, watching, stops itself (its consumer time after the last: 5 s, ten times the
    in-process rigs' 0.5 s, for the enable's own steps on a busy machine)."""
    sim, driver = driver_factory(make_config(1, host_timeout_ms=5000))
    drive, handle = driver.drive("joint1"), driver.buses["can0"]
    runner = sim.simulators["can0"]
    wait_for(lambda: handle.beats_sent() >= 3, 30.0, "three host heartbeats sent")
    send_beat = handle.beat
    monkeypatch.setattr(handle, "beat", lambda host: None)  # the supervisor's: never sent from here on
    drive.boot.boot()

    def two_beats(point: str) -> None:
        if point == "enable: host watch":
            for _ in range(2):
                send_beat(127)

    drive.channel.set_hook(two_beats)
    try:
        drive.enable(timeout_s=30.0)  # a bound for a hang: refused at its end if two were not enough
    finally:
        drive.channel.set_hook(None)
    assert runner.call(lambda: dict(runner.drive(1)._consumer_seen)), "enabled, but the drive is not watching the host"
    wait_for(lambda: runner.call(lambda: runner.drive(1).state) != State.OPERATION_ENABLED, 60.0,
             "the drive to stop itself with the host silent")
    assert not runner.call(lambda: dict(runner.drive(1)._consumer_seen))  # disarmed: its consumer tripped


def test_a_slow_host_heartbeat_still_lets_a_drive_be_enabled(sim_factory: SimFactory) -> None:
    """host_heartbeat_ms may be up to 1000: the two heartbeats a drive's watch needs after a boot
    then take up to two seconds, longer than enable's own 1 s timeout. The wait lasts at least
    WATCH_START_PERIODS periods, so the enable right after a boot succeeds (bounded by the enable's
    timeout alone, it was refused every time)."""
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                      "kwargs": {"host": "127.0.0.1", "port": 1}, "host_heartbeat_ms": 1000}],
                           "drives": [{"name": "joint1", "node_id": 1, "host_timeout_ms": 3000}]},
                          source=REPO / "tests" / "generated.yaml")
    _, cfg = sim_factory(config)
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        drive.boot.boot()  # told to watch again: the next two heartbeats, up to 2 s away
        drive.enable()
        assert drive.cache.state is State.OPERATION_ENABLED and not drive.watch.not_watching_yet()


def test_default_config_has_the_host_watch() -> None:
    config = load_config()
    assert config.buses[0].host_node_id == 127 and config.buses[0].host_heartbeat_s == 0.05
    assert config.drives[0].host_timeout_s == pytest.approx(0.15) and config.drives[0].on_host_loss == "quick_stop"


def test_sigterm_to_an_api_script_with_the_helper_stops_the_drive_in_the_driver(tmp_path: Path) -> None:
    drives = ROVER[:1]
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "wheel1", 4096)], port=0) as sim:
        config = write_config(tmp_path / "rover.yaml", sim.port, drives)
        with watching(sim, ["can0"]) as watches:
            proc = subprocess.Popen([sys.executable, str(CLIENT), str(config), "60", "--helper"], cwd=REPO,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            try:
                assert proc.stdout is not None and proc.stdout.readline().strip() == "READY"
            except BaseException:
                proc.kill()
                raise
            t_signal, out, err = signal_and_wait(proc, signal.SIGTERM, sim, watches)
        frames = watches["can0"].frames
    assert proc.returncode == 0 and f"STOPPED {int(signal.SIGTERM)}" in out, err
    stopped = first_stop(frames, 0x181, 0, t_signal)
    assert stopped is not None and stopped - t_signal < 0.5
    # the driver itself stopped it (quick stop, then disable voltage), not the drive's host watch
    cws = [int.from_bytes(m.data[:2], "little") for t, m in frames if t >= t_signal and m.arbitration_id == 0x201]
    assert cws[:2] == [0x02, 0x00], cws
    assert not [m for t, m in frames if m.arbitration_id == 0x81 and m.data[:2] == b"\x30\x81"]  # no EMCY 0x8130


def test_an_api_script_without_any_handler_is_still_stopped_by_the_drive(tmp_path: Path) -> None:
    run_and_stop(tmp_path, ROVER[:1], signal.SIGTERM)


def test_a_config_cannot_give_a_drive_the_hosts_node_id() -> None:
    from can_config import parse_config
    from can_config.errors import ConfigError

    with pytest.raises(ConfigError, match=r"drives\[0\]\.node_id: node id 127 is the host's own id"):
        parse_config({"buses": [{"name": "can0", "interface": "virtual", "channel": "x"}],
                      "drives": [{"name": "a", "node_id": 127}]})
    with pytest.raises(ConfigError, match=r"host_timeout_ms: got 40; it must be longer than the bus's host_heartbeat_ms \(50\)"):
        parse_config({"buses": [{"name": "can0", "interface": "virtual", "channel": "x"}],
                      "drives": [{"name": "a", "node_id": 1, "host_timeout_ms": 40}]})


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_to_rovercan_jog_stops_the_drive(tmp_path: Path, sig: int) -> None:
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "wheel1", 4096)], port=0) as sim:
        config = write_config(tmp_path / "rover.yaml", sim.port, ROVER[:1])
        runner = sim.simulators["can0"]
        sim_drive = runner.drive(1)
        with watching(sim, ["can0"]) as watches:
            proc = subprocess.Popen([sys.executable, "-m", "rovercan", "jog", "1", "60", "--for", "30",
                                     "--config", str(config)], cwd=REPO, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
            try:
                wait_for(lambda: abs(float(runner.call(lambda: sim_drive.omega))) > 1.0, 15.0, "the jog turning")  # type: ignore[arg-type]
            except BaseException:
                proc.kill()
                raise
            t_signal, _, err = signal_and_wait(proc, sig, sim, watches)
        frames = watches["can0"].frames
        final = runner.call(lambda: sim_drive.state.name)
    assert proc.returncode == 1, err
    assert f"stopped by {signal.Signals(sig).name}" in err and "Traceback" not in err, err
    stopped = first_stop(frames, 0x181, 0, t_signal)
    assert stopped is not None and stopped - t_signal < 0.5
    print(f"jog stopped {(stopped - t_signal) * 1000:.0f} ms after {signal.Signals(sig).name}")
    cws = [int.from_bytes(m.data[:2], "little") for t, m in frames if t >= t_signal and m.arbitration_id == 0x201]
    assert cws[:2] == [0x02, 0x00], cws  # the CLI's own quick stop and disable, before it exits
    assert final == "SWITCH_ON_DISABLED"


def seconds_until_stopped(sim: SimService, nodes: list[int], timeout_s: float = 2.0) -> dict[int, float]:
    """From now until each simulated drive has left Operation Enabled and stands still (its truth)."""
    runner = sim.simulators["can0"]
    t0 = time.monotonic()
    out: dict[int, float] = {}
    while len(out) < len(nodes) and time.monotonic() - t0 < timeout_s:
        for node in nodes:
            drive = runner.drive(node)
            state, omega = runner.call(lambda d=drive: (d.state.name, d.omega))  # type: ignore[misc]
            if node not in out and state != "OPERATION_ENABLED" and omega == 0.0:
                out[node] = time.monotonic() - t0
        time.sleep(0.002)
    return out


@pytest.mark.parametrize("failure", ["cable pulled", "bus server gone"])
def test_the_drives_stop_when_the_host_is_cut_off(driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]],
                                                 failure: str) -> None:
    from virtual_can.scenario import apply_action

    sim, driver = driver_factory(make_config(2, counts_per_rev=4096, gear_ratio=10, profile_acceleration_deg_s2=2000,
                                             watchdog_ms=10_000, host_timeout_ms=HOST_TIMEOUT_S * 1000))
    for drive in driver:
        drive.enable()
        drive.set_velocity(60.0)
    wait_for(lambda: all(abs(d.snapshot().velocity_deg_s - 60.0) < 3.0 for d in driver), 3.0, "both turning")
    if failure == "cable pulled":  # the drives' side of the cable: they hear nothing more
        for node in (1, 2):
            apply_action(sim, {"action": "unplug", "node": node})
    else:  # the socketcand server drops its clients: the drives keep running on the CAN bus
        apply_action(sim, {"action": "disconnect_clients"})
    stopped = seconds_until_stopped(sim, [1, 2])
    print(f"stop after {failure}: " + ", ".join(f"node {n} {dt * 1000:.0f} ms" for n, dt in stopped.items()))
    assert set(stopped) == {1, 2} and max(stopped.values()) <= BOUND_S, stopped


# ------------------------------------------------------------------ a ROS process of ours killed while it moves
#: A bound for a hang only: the verdicts below are outcomes and their order on the bus.
HANG_S = 30.0
HOST_HEARTBEAT = 0x77F  # node 127's


def host_frame(cob_id: int) -> bool:
    """A frame only the host sends: NMT, an RPDO (controlword or set-point), an SDO request, its
    heartbeat. The SYNC is left out: the bus daemon's timer sends it while a frozen process keeps
    its connection."""
    return (cob_id in (0x000, HOST_HEARTBEAT) or 0x600 < cob_id < 0x680
            or (cob_id & 0x780 in (0x200, 0x300, 0x400, 0x500) and cob_id & 0x7F != 0))


def all_threads_stopped(pid: int) -> bool:
    """Every thread of ``pid`` in the stopped state (``T`` in /proc/<pid>/task/*/stat)."""
    states = []
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        text = stat.read_text()
        states.append(text[text.rindex(")") + 2])
    return bool(states) and set(states) == {"T"}


@contextmanager
def host_process(argv: list[str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``argv`` run from the repository, its output to ``log`` (no pipe to fill and block it);
    killed at the end, thawed first if it was frozen."""
    with log.open("wb") as out:
        proc = subprocess.Popen(argv, cwd=REPO, stdout=out, stderr=subprocess.STDOUT,
                                env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
        try:
            yield proc
        finally:
            proc.kill()
            proc.send_signal(signal.SIGCONT)
            proc.wait(HANG_S)


def emcy_host_lost(frames: list[tuple[float, can.Message]], node: int, since: int) -> int | None:
    """Index of the first EMCY 0x8130 (heartbeat consumer: the host is lost) of ``node`` from ``since``."""
    for i in range(since, len(frames)):
        msg = frames[i][1]
        if msg.arbitration_id == 0x080 + node and bytes(msg.data[:2]) == b"\x30\x81":
            return i
    return None


def signal_the_host_and_see_the_drives_stop(proc: subprocess.Popen[bytes], sim: SimService,
                                            watches: dict[str, Watch], drives: list[tuple[str, int, str, Path]],
                                            sig: int) -> None:
    """``sig`` (SIGKILL or SIGSTOP) to the host's process ``proc`` while its drives are Operation
    Enabled and moving; its end or freeze awaited. Then, on the bus, for each drive: its EMCY
    0x8130 (its host-heartbeat consumer tripped) after the signal, and no frame of the host after
    it while the drive's own heartbeats go on (it stopped itself: nothing of ours ran); and the
    test's own SDO client reads it not Operation Enabled and at velocity 0."""
    marks = {ch: len(w.frames) for ch, w in watches.items()}
    proc.send_signal(sig)
    if sig == signal.SIGKILL:
        assert proc.wait(HANG_S) == -signal.SIGKILL
    else:
        wait_for(lambda: all_threads_stopped(proc.pid), HANG_S, "every thread of the host frozen")
    for name, node, ch, _ in drives:
        frames = watches[ch].frames
        wait_for(lambda frames=frames, node=node, mark=marks[ch]: emcy_host_lost(frames, node, mark) is not None,
                 HANG_S, f"{name}: EMCY 0x8130 (host lost) on the bus")
        tripped = emcy_host_lost(frames, node, marks[ch])
        assert tripped is not None
        wait_for(lambda frames=frames, node=node, tripped=tripped:
                 sum(m.arbitration_id == 0x700 + node for _, m in frames[tripped:]) >= 2,
                 HANG_S, f"{name}: two of its heartbeats after its EMCY")
        after = [f"0x{m.arbitration_id:03X} {bytes(m.data).hex()}" for _, m in frames[tripped:]
                 if host_frame(m.arbitration_id)]
        assert not after, f"{name}: the host sent after the drive stopped itself: {after[:5]}"
    for ch in sorted({ch for _, _, ch, _ in drives}):
        network = canopen.Network()
        network.connect(interface="socketcand", channel=ch, host=sim.host, port=sim.port)
        try:
            for name, node, chan, eds in drives:
                if chan == ch:
                    check_still_and_not_enabled(network.add_node(node, load_drive_od(eds, node)), name)
        finally:
            network.disconnect()


def check_still_and_not_enabled(remote: canopen.RemoteNode, name: str) -> None:
    """The drive, asked by SDO until it answers so (a hang bound), is not Operation Enabled and at velocity 0."""
    read: list[tuple[int, int]] = []

    def stopped() -> bool:
        try:
            sw = int.from_bytes(remote.sdo.upload(0x6041, 0), "little")
            velocity = int.from_bytes(remote.sdo.upload(0x606C, 0), "little", signed=True)
        except canopen.SdoCommunicationError:
            return False  # not answered in time on a busy machine: ask again
        read.append((sw, velocity))
        return not statusword_enabled(sw) and velocity == 0

    wait_for(stopped, HANG_S, f"{name}: not Operation Enabled and still, read by SDO",
             lambda: f"statusword, velocity: {[(hex(sw), v) for sw, v in read[-3:]]}")

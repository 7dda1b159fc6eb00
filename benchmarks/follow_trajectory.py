"""A six-joint arm following a trajectory at 500 Hz beside the rover's wheels (issue 65), two ways:

* ``action``: the trajectory sent once as a control_msgs/FollowJointTrajectory goal to
  ``/arm_controller/follow_joint_trajectory``; the driver samples it at each SYNC (motor_driver/follow.py).
* ``stream``: the same set-points (the same spline, sampled every 2 ms) published on ``/joint_commands``
  at 500 Hz from another process, as a team's own interpolator node would.

Three processes as on a bench (benchmarks/stack_run.py's): the simulator (``rovercan sim``), the driver
(``rover_driver``, measured: its CPU from /proc), and this one (the action client, an independent
python-can listener on the arm's bus); the stream's publisher is a fourth (its CPU is counted too).
The config is bus_limit.py's twelve drives (config/rover.yaml's wheels on can0 and can1 at 100 Hz,
six joints on can2 at 500 Hz) with the arm's joints limited (a trajectory group's joints are).

Figures per way, from the listener's frames (the server's wire stamps), for the arm's joints:
* ``following_rms_deg`` / ``following_max_deg``: each position TPDO against the latest set-point of its
  joint on the wire (how closely the drives follow what they were sent);
* ``duration_s``: from the run's first arm set-point to its last (the trajectory's ``trajectory_s``:
  longer when SYNCs went without a set-point);
* ``periods_one`` / ``periods_none`` / ``periods_two_plus``: of the SYNC periods of the run, the share in
  which a joint got exactly one set-point, none (the drive held: a stall), two or more (one was lost);
* ``cpu_core_fraction``: CPU seconds of the driver (plus the publisher, for ``stream``) over the run's wall time.

``python benchmarks/follow_trajectory.py [--seconds S]`` prints the figures as JSON, by hand. ``--six``: run.py's
reference instead (:func:`six_following`: six drives on one bus at 500 Hz following a goal, the driver's CPU).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import yaml

os.environ.setdefault("ROS_DOMAIN_ID", str(70 + os.getpid() % 30))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bus_limit
import stack_run
from stack_run import REPO, proc_cpu_s, simulator, unboosted

sys.path.insert(0, str(REPO))
from motor_driver.follow.trajectory import Spline, sample_times

JOINTS = [f"j{i}" for i in range(1, 7)]
AMPLITUDE_DEG = 30.0
PERIOD_S = 0.002
ARM_BUS = bus_limit.ARM_BUS


def arm_config(config: dict[str, Any], bus: str) -> str:
    """``config`` with the joints on ``bus`` limited to +-170 deg (a trajectory group's joints are) and
    grouped as ``arm_controller``."""
    for drive in config["drives"]:
        if drive["bus"] == bus:
            drive.update(joint="limited", min_deg=-170.0, max_deg=170.0)
    config["trajectory_groups"] = [{"name": "arm_controller", "joints": JOINTS}]
    return yaml.safe_dump(config, sort_keys=False)


def config_text() -> str:
    """bus_limit's twelve drives, the arm's six on ``can2`` as the group."""
    return arm_config(yaml.safe_load(bus_limit.twelve_config_text()), ARM_BUS)


def spline(seconds: float) -> Spline:
    """Joint i: a half-sine of AMPLITUDE_DEG (alternating sign), positions and velocities every 0.1 s."""
    times = [seconds * k / 40 for k in range(41)]
    w = math.pi / seconds
    knots = tuple(tuple(((-1) ** i * AMPLITUDE_DEG * math.sin(w * t), (-1) ** i * AMPLITUDE_DEG * w * math.cos(w * t),
                         None) for i in range(6)) for t in times)
    return Spline(tuple(times), knots)


class Listener:
    """Every frame of the arm's bus, with the server's wire stamp."""

    def __init__(self, port: int, channel: str = ARM_BUS) -> None:
        self.frames: list[can.Message] = []
        self.bus = can.Bus(interface="socketcand", channel=channel, host="127.0.0.1", port=port)
        self.notifier = can.Notifier(self.bus, [self.frames.append], timeout=0.1)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def figures(frames: list[can.Message], seconds: float, counts_per_deg: float) -> dict[str, Any]:
    """Tracking and delivery of one run's frames, from its first arm set-point to its last."""
    setpoint_ids = {0x300 + n for n in range(1, 7)}
    first = next(m.timestamp for m in frames if m.arbitration_id in setpoint_ids)
    last = max(m.timestamp for m in frames if m.arbitration_id in setpoint_ids)
    window = [m for m in frames if first - PERIOD_S <= m.timestamp <= last]
    target: dict[int, int] = {}
    errors: list[float] = []
    periods = {"one": 0, "none": 0, "two_plus": 0}
    counts: dict[int, int] | None = None
    for m in window:
        cob = m.arbitration_id
        if cob == 0x080:
            if counts is not None:
                for node in range(1, 7):
                    n = counts.get(node, 0)
                    periods["one" if n == 1 else "none" if n == 0 else "two_plus"] += 1
            counts = {}
        elif cob in setpoint_ids:
            target[cob - 0x300] = int.from_bytes(m.data[2:6], "little", signed=True)
            if counts is not None:
                counts[cob - 0x300] = counts.get(cob - 0x300, 0) + 1
        elif 0x281 <= cob <= 0x286 and cob - 0x280 in target:  # the measured position against its latest target
            errors.append(abs(int.from_bytes(m.data[:4], "little", signed=True) - target[cob - 0x280]) / counts_per_deg)
    total = max(sum(periods.values()), 1)
    return {"following_rms_deg": math.sqrt(sum(e * e for e in errors) / len(errors)),
            "following_max_deg": max(errors), "duration_s": last - first, "trajectory_s": seconds,
            **{f"periods_{k}": v / total for k, v in periods.items()}}


def publish_stream(seconds: float) -> None:
    """The stream's publisher (its own process): the spline's set-points on /joint_commands every 2 ms."""
    import rclpy
    from sensor_msgs.msg import JointState

    from nodes.process.qos import SETPOINT_QOS

    rclpy.init()
    node = rclpy.create_node("bench_stream")
    pub = node.create_publisher(JointState, "/joint_commands", SETPOINT_QOS)
    deadline = time.monotonic() + 10
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    path = spline(seconds)
    start = time.monotonic()
    for t in sample_times(seconds, PERIOD_S):
        time.sleep(max(0.0, start + t - time.monotonic()))
        pub.publish(JointState(name=JOINTS, position=[math.radians(p) for p, _, _ in path.sample(t)]))
    rclpy.shutdown()


def run_action(client: Any, seconds: float) -> None:
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from trajectory_msgs.msg import JointTrajectoryPoint

    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = JOINTS
    path = spline(seconds)
    for t in path.times_s:
        sample = path.sample(t) if t < seconds else tuple((p, 0.0, 0.0) for p, _, _ in path.sample(t))
        goal.trajectory.points.append(JointTrajectoryPoint(
            positions=[math.radians(p) for p, _, _ in sample], velocities=[math.radians(v) for _, v, _ in sample],
            time_from_start=Duration(sec=int(t), nanosec=int(t % 1 * 1e9))))
    done = threading.Event()
    outcome: list[Any] = []

    def on_result(future: Any) -> None:
        outcome.append(future.result().result)
        done.set()

    def on_goal(future: Any) -> None:
        future.result().get_result_async().add_done_callback(on_result)
    client.send_goal_async(goal).add_done_callback(on_goal)
    if not done.wait(seconds + 30):
        raise RuntimeError("no result")
    if outcome[0].error_code != 0:
        raise RuntimeError(f"the goal failed: {outcome[0].error_string}")


def six_config_text() -> str:
    """bus_limit.py's six drives on one bus at 500 Hz, the joints limited and one trajectory group."""
    return arm_config(yaml.safe_load(bus_limit.config_text()), "can0")


@contextmanager
def following(template: Path, channel: str, *sim_args: str) -> Iterator[tuple[subprocess.Popen[bytes], Any, Listener]]:
    """The simulator on ``template`` (``sim_args`` more of its arguments), the driver as deployed on
    it (armed), a listener on ``channel`` and an action client whose server is up, the drives
    armed; all ended after."""
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor

    from nodes.process.spinning import SpinThread

    with simulator("--config", str(template), *sim_args) as port, tempfile.TemporaryDirectory() as tmp:
        config = stack_run.on_port(template, port, tmp)
        listener = Listener(port, channel)
        driver = subprocess.Popen(unboosted([sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p",
                                             f"config:={config}", "-p", "arm:=true", "-p", "diagnostics_rate_hz:=2.0"]),
                                  cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_follow", context=context)
        client = ActionClient(node, FollowJointTrajectory, "/arm_controller/follow_joint_trajectory")
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spin = SpinThread(executor, "bench-client")
        try:
            if not client.wait_for_server(timeout_sec=60):
                raise stack_run.StartFailed("the driver serves no /arm_controller/follow_joint_trajectory")
            time.sleep(3.0)  # every drive armed (the twelve's wheels streaming)
            yield driver, client, listener
        finally:
            spin.stop(5.0)
            context.try_shutdown()
            driver.terminate()
            driver.wait(30)
            listener.close()


def six_following(seconds: float) -> dict[str, Any]:
    """run.py's reference: bus_limit.py's six drives at 500 Hz following one FollowJointTrajectory
    goal (the driver samples it at each SYNC: no ROS message a set-point), measured as the stack run
    measures (the node as deployed, the simulator's drive models in processes of their own, the
    driver's CPU from /proc over ``seconds`` in the goal's middle). The canopen library's same work is
    bus_limit's (the same bus, drives, SYNC and set-point rate). ``periods_none``: the share of SYNC
    periods in which a joint got no set-point (the work not done, judged by run.py)."""
    failed: list[BaseException] = []

    def follow(client: Any) -> None:
        try:
            run_action(client, seconds + 4.0)
        except Exception as err:  # the goal's failure, said by the figures
            failed.append(err)

    with bus_limit.limit_config(text=six_config_text()) as template, \
            following(template, "can0", "--drive-processes") as (driver, client, listener):
        goal = threading.Thread(target=follow, args=(client,), daemon=True)
        goal.start()
        time.sleep(2.0)  # the goal under way
        mark, cpu0, t0 = len(listener.frames), proc_cpu_s(driver.pid), time.monotonic()
        time.sleep(seconds)
        cpu, wall = proc_cpu_s(driver.pid) - cpu0, time.monotonic() - t0
        window = listener.frames[mark:]
        goal.join(seconds + 40.0)
        if failed or goal.is_alive():
            raise RuntimeError(f"the goal did not succeed: {failed[0] if failed else 'no result'}")
    tracked = figures(window, seconds, 4096 * 50 / 360)
    return {"cpu_core_fraction": round(cpu / wall, 4), "periods_none": round(tracked["periods_none"], 4),
            "following_rms_deg": round(tracked["following_rms_deg"], 4)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="the trajectory's duration")
    parser.add_argument("--six", action="store_true", help="run.py's reference: six drives at 500 Hz following a goal")
    args = parser.parse_args()
    if args.six:
        stack_run.harness_ahead()
        print(json.dumps(six_following(args.seconds), indent=2))
        return 0
    stack_run.harness_ahead()
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(dir=REPO / "benchmarks" / "out" if (REPO / "benchmarks" / "out").is_dir() else None) as tmp:
        template = Path(tmp) / "arm.yaml"
        template.write_text(config_text())
        with following(template, ARM_BUS) as (driver, client, listener):
            cpd = 4096 * 50 / 360
            for way in ("action", "stream"):
                mark = len(listener.frames)
                cpu0, t0 = proc_cpu_s(driver.pid), time.monotonic()
                if way == "action":
                    run_action(client, args.seconds)
                    extra = 0.0
                else:
                    peer = subprocess.Popen(unboosted([sys.executable, __file__, "--publisher-run", str(args.seconds)]),
                                            cwd=REPO)
                    _, _, usage = os.wait4(peer.pid, 0)  # the publisher's whole CPU time
                    extra = usage.ru_utime + usage.ru_stime
                time.sleep(0.5)
                wall = time.monotonic() - t0
                cpu = proc_cpu_s(driver.pid) - cpu0 + extra
                results[way] = {**figures(listener.frames[mark:], args.seconds, cpd), "cpu_core_fraction": cpu / wall}
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--publisher-run":
        publish_stream(float(sys.argv[2]))
        sys.exit(0)
    sys.exit(main())

"""Services that never die (issue 70): a value a reply cannot carry, an odd write, or any exception
in a service, timer or subscription callback is answered or counted, logged once with its trace,
said on /diagnostics, and every service (/arm and each joint's) still answers after it. A real
rclpy graph: the driver's process as the assembly builds it (nodes/assembly.py), simulated drives
on the bus, real rclpy service clients on a node spun by an executor of its own.

The landed code: one ``<joint>/sdo_read`` of a REAL32 holding NaN raised ``ValueError`` in the
services' MultiThreadedExecutor, which re-raised it out of its spin: no joint's enable or set_mode
was answered again."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes

from can_config import GENERIC_EDS, with_bus_overrides
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import HAVE_ROS, make_config, requires_ros, wait_for

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rcl_interfaces.srv import SetParameters, SetParametersAtomically
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rovercan_msgs.srv import SdoRead, SdoWrite, SetMode
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from nodes.assembly import Assembly
    from nodes.process import spinning
    from nodes.process.qos import DIAGNOSTICS_QOS, SETPOINT_QOS, STATE_QOS

JOINTS = ["joint1", "joint2"]
#: A bound for a hang: every answer comes much sooner, later on a crowded machine.
HANG_S = 30.0
#: Objects the test EDS adds to the generic drive: a REAL32, an UNSIGNED64 and a REAL64.
REAL32, U64, REAL64 = 0x2100, 0x2101, 0x2102


def odd_eds(path: Path) -> Path:
    """The generic drive with a REAL32, an UNSIGNED64 and a REAL64 object (read-write)."""
    od = canopen.import_od(str(GENERIC_EDS), 1)
    for index, name, data_type in ((REAL32, "Real32 value", datatypes.REAL32), (U64, "Unsigned64 value",
                                   datatypes.UNSIGNED64), (REAL64, "Real64 value", datatypes.REAL64)):
        var = ODVariable(name, index)
        var.data_type, var.access_type, var.default = data_type, "rw", 0
        od.add_object(var)
    canopen.export_od(od, str(path), doc_type="eds")
    return path


class Rig:
    """The assembly on the simulator, and a probe node with a client per service."""

    def __init__(self, sim: SimService, assembly: Assembly, probe: Any) -> None:
        self.sim, self.assembly, self.probe = sim, assembly, probe
        self.clients: dict[str, Any] = {}
        self.diagnostics: list[Any] = []
        probe.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, DIAGNOSTICS_QOS)

    def call(self, srv_type: Any, name: str, request: Any = None) -> Any:
        client = self.clients.get(name)
        if client is None:
            client = self.clients[name] = self.probe.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=HANG_S), f"no service {name}"
        future = client.call_async(request if request is not None else srv_type.Request())
        wait_for(future.done, HANG_S, f"an answer of {name}")
        return future.result()

    def hold(self, joint: str, index: int, value: float | int) -> None:
        """The simulated drive of ``joint`` holds ``value`` in ``index``:0 (set from outside the driver)."""
        runner = self.sim.simulators["can0"]
        node_id = self.assembly.driver.drive(joint).node_id
        runner.call(lambda: runner.drive(node_id).store.set(index, 0, value))

    def driver_status(self) -> dict[str, str] | None:
        """The newest "rovercan: driver" status's values, or None."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name == "rovercan: driver":
                    return {kv.key: kv.value for kv in status.values} | {"level": str(status.level[0]),
                                                                        "message": status.message}
        return None

    def every_service_answers(self) -> None:
        """/arm, and each joint's enable, set_mode, sdo_read and quick_stop, answer."""
        assert self.call(Trigger, "arm").message.startswith("arm")
        for joint in JOINTS:
            assert self.call(Trigger, f"{joint}/enable").success
            assert self.call(SetMode, f"{joint}/set_mode", SetMode.Request(mode="profile_position")).message
            read = self.call(SdoRead, f"{joint}/sdo_read", SdoRead.Request(index=0x1000, subindex=0))
            assert read.success and read.value == 0x0002_0192, read.message
            assert self.call(Trigger, f"{joint}/quick_stop").success


def said_once(caplog: pytest.LogCaptureFixture, what: str) -> None:
    """``what`` logged with its trace once; any other line of it (at most one every
    runtime.REPEAT_LOG_S while it keeps failing) says it again, without the trace."""
    lines = [r for r in caplog.records if what in r.getMessage()]
    traced = [r for r in lines if r.exc_info is not None]
    assert len(traced) == 1 and lines[0] is traced[0], [r.getMessage() for r in lines]
    assert all(" again " in r.getMessage() for r in lines[1:]), [r.getMessage() for r in lines]


@pytest.fixture
def rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Rig]:
    monkeypatch.setattr(spinning, "IDLE_POLL_S", 600.0)  # the idle executors never poll: a call must wake them
    config = make_config(len(JOINTS), eds=str(odd_eds(tmp_path / "odd.eds")))
    sim = SimService.from_config(config, port=0)
    context = rclpy.Context()
    rclpy.init(context=context)
    hot = spinning.make_executor("events", context)
    assembly = Assembly(MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)), hot, context=context,
                        overrides=[Parameter("diagnostics_rate_hz", value=10.0)])
    probe = rclpy.create_node("probe", context=context)
    probe_executor = SingleThreadedExecutor(context=context)
    probe_executor.add_node(probe)
    spins: list[spinning.SpinThread] = []
    try:
        assembly.build()
        assembly.start()
        spins = [spinning.SpinThread(hot, "test-hot", assembly.failures),
                 spinning.SpinThread(probe_executor, "test-probe")]
        yield Rig(sim, assembly, probe)
    finally:
        for spin in spins:
            spin.stop(5.0)
        assembly.close()
        probe.destroy_node()
        rclpy.shutdown(context=context)
        sim.close()


def test_sdo_reads_of_values_an_int64_cannot_carry_are_answered_as_text(rig: Rig) -> None:
    """NaN, the infinities, 1e30 (REAL32 and REAL64) and UNSIGNED64 values above int64: each
    answered, value 0, the text saying it; then every service answers."""
    held = [(REAL32, math.nan, "nan"), (REAL32, math.inf, "inf"), (REAL32, -math.inf, "-inf"),
            (REAL32, 1e30, None),
            (REAL64, 1e30, "1e+30"), (REAL64, -1e300, "-1e+300"), (U64, 2**64 - 1, str(2**64 - 1)),
            (U64, 2**63, str(2**63))]
    for index, value, text in held:
        rig.hold("joint1", index, value)
        read = rig.call(SdoRead, "joint1/sdo_read", SdoRead.Request(index=index, subindex=0))
        assert read.success and read.value == 0, (value, read)
        if text is not None:
            assert read.text == text, (value, read)
        else:  # a REAL32 holds 1e30 as its nearest float32
            assert float(read.text) == pytest.approx(1e30, rel=1e-6), read
        assert "int64 cannot carry it" in read.message, read.message
    rig.hold("joint1", U64, 2**63 - 1)  # the largest an int64 carries: carried
    read = rig.call(SdoRead, "joint1/sdo_read", SdoRead.Request(index=U64, subindex=0))
    assert read.value == 2**63 - 1 and read.text == str(2**63 - 1) and "cannot" not in read.message
    rig.hold("joint1", REAL32, -2.75)
    read = rig.call(SdoRead, "joint1/sdo_read", SdoRead.Request(index=REAL32, subindex=0))
    assert (read.value, read.text) == (-2, "-2.75")
    rig.every_service_answers()
    assert rig.assembly.failures.snapshot()[0] == 0  # each answered by the service itself: no failure


ODD_WRITES = [(U64, -1), (REAL32, 2**63 - 1), (REAL32, -(2**63)), (REAL64, 7), (0x1008, 12345),  # a string object
              (0x6060, 300), (0x6060, -200), (0x1017, -1), (0x2345, 1), (0x1000, 1), (0x6040, 15), (0x607A, 99999)]


def test_odd_sdo_writes_are_each_answered_and_every_service_answers_after(rig: Rig) -> None:
    for index, value in ODD_WRITES:
        reply = rig.call(SdoWrite, "joint2/sdo_write", SdoWrite.Request(index=index, subindex=0, value=value))
        assert reply.message, (index, value, reply)
    read = rig.call(SdoRead, "joint2/sdo_read", SdoRead.Request(index=REAL32, subindex=0))
    assert read.success and read.text == repr(float(-(2**63))), read  # the last written, as a REAL32
    assert read.value == -(2**63)  # the smallest int64: carried
    rig.every_service_answers()


def test_a_raising_service_callback_answers_naming_itself_and_is_counted_once(
        rig: Rig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Any exception (not one of the project's) in a service: a failed answer naming the service,
    one ERROR line with its trace, callback_failures 1 on /diagnostics; every service answers after."""
    caplog.set_level(logging.INFO)

    def boom(*args: object) -> object:
        raise RuntimeError("Boom in sdo_read")

    monkeypatch.setattr(rig.assembly.driver.drive("joint1").sdo, "read_value", boom)
    reply = rig.call(SdoRead, "joint1/sdo_read", SdoRead.Request(index=0x1000, subindex=0))
    assert not reply.success and "/joint1/sdo_read" in reply.message and "Boom in sdo_read" in reply.message
    monkeypatch.undo()
    rig.every_service_answers()
    lines = [r for r in caplog.records if "Boom" in r.getMessage() and r.levelno >= logging.ERROR]
    assert len(lines) == 1 and lines[0].exc_info is not None, [r.getMessage() for r in lines]
    wait_for(lambda: (rig.driver_status() or {}).get("callback_failures") == "1", HANG_S, "the failure on /diagnostics")
    status = rig.driver_status()
    assert status is not None and "/joint1/sdo_read" in status["last_callback_failure"]
    assert status["level"] == "1" and "callback failure" in status["message"]


def test_a_raising_parameter_check_fails_each_parameter_as_rclpy_answers(rig: Rig) -> None:
    """rclpy's own parameter service raises when a node's set-parameters check does: the supervised
    answer is then rclpy's for a parameter it cannot set, a failed result naming the failure for
    that parameter and each after it, the results of those set before it kept (an empty ``results``
    broke clients that read ``results[0]``, as ``ros2 param set`` does); a failed result for the
    atomic service; and a set works again after."""
    from rcl_interfaces.msg import SetParametersResult

    node = rig.assembly.node
    assert node is not None

    def boom(parameters: list[Parameter]) -> SetParametersResult:
        if any(p.value == 4.0 for p in parameters):
            raise RuntimeError("Boom in the parameter check")
        return SetParametersResult(successful=True)
    node.add_on_set_parameters_callback(boom)
    wanted = [Parameter("diagnostics_rate_hz", value=5.0).to_parameter_msg(),
              Parameter("diagnostics_rate_hz", value=4.0).to_parameter_msg(),
              Parameter("diagnostics_rate_hz", value=3.0).to_parameter_msg()]
    name = node.get_fully_qualified_name()
    reply = rig.call(SetParameters, f"{name}/set_parameters", SetParameters.Request(parameters=wanted))
    assert [r.successful for r in reply.results] == [True, False, False], reply
    assert all("set_parameters" in r.reason and "Boom in the parameter check" in r.reason for r in reply.results[1:])
    assert node.get_parameter("diagnostics_rate_hz").value == 5.0  # the first was set, as its result says
    atomic = rig.call(SetParametersAtomically, f"{name}/set_parameters_atomically",
                      SetParametersAtomically.Request(parameters=wanted))
    assert not atomic.result.successful and "Boom in the parameter check" in atomic.result.reason
    node.remove_on_set_parameters_callback(boom)
    reply = rig.call(SetParameters, f"{name}/set_parameters", SetParameters.Request(parameters=wanted[1:2]))
    assert [r.successful for r in reply.results] == [True], reply
    assert node.get_parameter("diagnostics_rate_hz").value == 4.0


def test_a_raising_timer_and_subscription_never_end_the_hot_executor(
        rig: Rig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The state timer and the /joint_commands subscription raise (on the hot EventsExecutor): each
    counted and said on /diagnostics, which the same executor goes on publishing; the states come
    back once the timer stops raising."""
    caplog.set_level(logging.INFO)
    node = rig.assembly.node
    assert node is not None
    raised: list[int] = []

    def boom() -> None:
        raised.append(1)
        raise RuntimeError("Boom in the state timer")

    monkeypatch.setattr(node, "_publish_states", boom)
    wait_for(lambda: len(raised) >= 3, HANG_S, "the state timer raising again and again")
    monkeypatch.undo()

    def refuse(*args: object) -> None:
        raise RuntimeError("Boom in /joint_commands")

    monkeypatch.setattr(node.refusals, "refuse", refuse)
    commands = rig.probe.create_publisher(JointState, "/joint_commands", SETPOINT_QOS)
    wait_for(lambda: commands.get_subscription_count() > 0, HANG_S, "/joint_commands matched")
    commands.publish(JointState(name=["no_such_joint"], position=[0.0]))
    wait_for(lambda: "/joint_commands" in (rig.driver_status() or {}).get("last_callback_failure", ""), HANG_S,
             "the subscription's failure on /diagnostics")
    monkeypatch.undo()
    status = rig.driver_status()
    assert status is not None and int(status["callback_failures"]) == len(raised) + 1
    said_once(caplog, "Boom in the state timer")  # however often it raised
    states: list[Any] = []
    rig.probe.create_subscription(JointState, "/joint_states", states.append, STATE_QOS)
    wait_for(lambda: bool(states), HANG_S, "/joint_states after the timer raised")
    rig.every_service_answers()


def test_a_failing_hook_of_the_state_timer_is_counted_and_the_states_go_on(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    """A hook on the state timer (the drive system's control loop runs there) that raises: the
    states are published all the same, the failure counted on /diagnostics and said once with its
    trace (it was a throttled line, never counted)."""
    caplog.set_level(logging.INFO)
    node = rig.assembly.node
    assert node is not None
    raised: list[int] = []

    def hook() -> None:
        raised.append(1)
        raise RuntimeError("Boom in a tick hook")

    assert node.share_tick(node.state_period_s, hook)
    states: list[Any] = []
    rig.probe.create_subscription(JointState, "/joint_states", states.append, STATE_QOS)
    wait_for(lambda: len(states) >= 3 and len(raised) >= 3, HANG_S, "states published while the hook raises")

    def said() -> bool:
        status = rig.driver_status() or {}
        return "Boom in a tick hook" in status.get("last_callback_failure", "") and \
            int(status.get("callback_failures", "0")) >= 3

    wait_for(said, HANG_S, "the hook's failures counted on /diagnostics")
    said_once(caplog, "Boom in a tick hook")


@pytest.mark.parametrize("given", [True, False], ids=["failures given", "the node's"])
@pytest.mark.parametrize("kind", ["events", "single", "multi"])
def test_a_callback_that_escapes_supervision_never_ends_the_spin(kind: str, given: bool,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """A callback no one wrapped (an action server's internals, a node made later) raises on every
    call: rclpy's executors raise it out of their spin; spin_until counts it (in the failures it is
    given, else in those of the executor's driver node: rover_lifecycle's hot spin), says it once
    (rclpy's EventsExecutor says it itself, with its trace) and spins on."""
    import threading

    from rclpy.executors import MultiThreadedExecutor

    caplog.set_level(logging.INFO)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("raising", context=context)
    executor = (spinning.make_executor("events", context) if kind == "events" else
                SingleThreadedExecutor(context=context) if kind == "single" else
                MultiThreadedExecutor(num_threads=2, context=context))
    executor.add_node(node)
    calls: list[int] = []

    def tick() -> None:
        calls.append(1)
        raise RuntimeError("Boom unsupervised")

    node.create_timer(0.01, tick)
    failures = spinning.CallbackFailures()
    node.callback_failures = failures  # type: ignore[attr-defined]  # as a DriverNode carries them
    stop = threading.Event()
    spin = threading.Thread(target=spinning.spin_until, args=(executor, stop, 0.1, failures if given else None),
                            name="test-spin")
    spin.start()
    try:
        wait_for(lambda: failures.snapshot()[0] >= 3, HANG_S, "three failures counted, the spin going on")
        assert spin.is_alive()
    finally:
        stop.set()
        spin.join(HANG_S)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
    ours = [r for r in caplog.records if r.name == "nodes.process.spinning" and "Boom unsupervised" in r.getMessage()]
    assert len(ours) == (0 if kind == "events" else 1), [r.getMessage() for r in ours]


def test_a_step_that_fails_every_time_is_waited_on_never_a_busy_loop() -> None:
    """A failure at every step (here the executor's own, not a callback's) is counted and the
    loop waits ``poll_s`` before each next step (a busy loop would take a real-time core whole);
    it never ends the loop: the stop does. The old loop stepped again at once."""
    import threading

    class Waits(threading.Event):
        count = 0

        def wait(self, timeout: float | None = None) -> bool:
            self.count += 1
            return super().wait(timeout)

    stop = Waits()

    class Broken(SingleThreadedExecutor):
        steps = 0

        def spin_once(self, timeout_sec: float | None = None) -> None:
            self.steps += 1
            if self.steps == 6:
                stop.set()
            raise RuntimeError("the executor itself is broken")

    context = rclpy.Context()
    rclpy.init(context=context)
    executor = Broken(context=context)
    failures = spinning.CallbackFailures()
    try:
        spinning.spin_until(executor, stop, 0.001, failures)
    finally:
        executor.shutdown(timeout_sec=1.0)
        rclpy.shutdown(context=context)
    assert executor.steps == 6 and failures.snapshot()[0] == 6
    assert stop.count >= executor.steps - 1, stop.count  # a wait before every step after the first failure

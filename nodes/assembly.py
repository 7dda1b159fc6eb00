"""The driver's ROS process, put together in one place for every entry point: ``rover_driver``,
``rover_lifecycle`` (its transitions are this assembly's steps), ``motor_controller`` (the same,
restricted to one joint) and ``rovercan demo``. They choose from it; none builds its own.

Start order (:meth:`Assembly.build`, then :meth:`Assembly.start`):
1. every ROS entity (nodes, topics, services, actions, timers, executors): making them holds the
   interpreter (rclpy's C++ under the GIL) for up to a second on a slow machine; made after the
   driver had started, they held its heartbeat, and every drive's host watch tripped in 2 of 10
   launches of the shipped rover. Nothing is sent on the bus yet.
2. the driver started (another master looked for, every drive booted: the host watch armed).
3. the executors' threads, then ``arm`` if the node's parameter asks (the lifecycle: at activate).

Executors and callback groups (measured: docs/ros.md, README):
- hot (the caller spins it, on its own thread): the driver node (commands, state, diagnostics,
  parameters) and the drive system: rclpy's EventsExecutor (parameter ``executor``).
- ``rovercan-stops``: the stops alone, single-threaded: nothing but a stop is ahead of a stop.
- ``rovercan-services``: the services that wait (enable, recover, home, set_mode, SDO, /arm) on a
  MultiThreadedExecutor, a MutuallyExclusiveCallbackGroup per joint and one for /arm, a thread per
  group: one joint's homing (up to ``homing_timeout_s``) holds no other joint's services. (Its
  threads wait in rcl when idle; the hot path never runs on it.)
- ``rovercan-actions``: the actions' goals, coroutines on a single-threaded executor, the trajectory
  groups' FollowJointTrajectory among them (each group's set-points go out from a thread of its own,
  ``rovercan-follow-<group>``, at its bus's SYNC: :mod:`motor_driver.follow`).
- ``rovercan-handoff_N``: not an executor; the driver node's workers for a command that must wait
  for its drive (a mode switch, a target by SDO), one joint's at a time, made when first needed
  (:mod:`nodes.joints.handoff`): the hot thread never waits for a drive.

Callbacks (nodes/process/spinning.py, :func:`~nodes.process.spinning.supervise`): every service, timer and
subscription callback of the assembly's nodes is supervised, at :meth:`Assembly.build` and again
at :meth:`Assembly.start`: an unexpected exception is logged once with its trace, counted in the
driver node's /diagnostics (``callback_failures``), a service answers a failed response naming
itself, and no executor ends on one (each executor thread's spin, and the caller's spin of the
hot one given :attr:`Assembly.failures`, catch what still escapes).

Stop (:meth:`Assembly.close`): the driver closed first (its one safe stop,
:meth:`motor_driver.MotorDriver.safe_stop`: every drive quick-stopped and its voltage disabled;
a service blocked on a drive then fails fast), the executor threads joined, the nodes destroyed.
The rclpy context is the caller's to shut down.

The process set-up (:func:`set_up`), the same for every entry point (:func:`run` for
``rover_driver`` and ``motor_controller``, ``rover_lifecycle``, ``rovercan demo``): from the entry
point's own node, whose ``executor`` and ``realtime_priority`` it declares and reads, every thread
under SCHED_FIFO (before the driver's threads exist: each inherits it) and the hot executor. The
heap is settled by :meth:`Assembly.build` once everything lasting exists.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Collection, Sequence
from typing import Any, NamedTuple

import rclpy
from rclpy.context import Context
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from can_config import RoverConfig, load_config, simulated_config
from can_config.errors import RovercanError
from motor_driver import MotorDriver, StopReport
from motor_driver.follow import TrajectoryGroup, groups_of
from motor_driver.process import heap
from motor_driver.process.stop import StopSignal, teardown
from nodes.actions.driver_actions import DriverActionsNode
from nodes.joints.driver_node import DriverNode
from nodes.joints.driver_services import SERVICE_JOIN_S, DriverServicesNode, DriverStopsNode
from nodes.process import spinning
from nodes.process.logbridge import RclpyLogHandler, bridge_core_logging, unbridge
from nodes.process.params import PROCESS, declare
from nodes.rover.drive_system import DriveSystemNode

logger = logging.getLogger(__name__)

#: The threads of the executors beside the hot one, by the node each spins.
THREADS = {"rovercan_driver_stops": "rovercan-stops", "rovercan_driver_services": "rovercan-services",
           "rovercan_driver_actions": "rovercan-actions"}


class Process(NamedTuple):
    """What :func:`set_up` made of the process."""
    hot: Executor  #: the hot executor, of the ``executor`` parameter
    realtime: bool  #: every thread under SCHED_FIFO now


def set_up(node: Node) -> Process:
    """The process set-up of every entry point, from ``node`` (the entry point's own, made before
    the driver): its ``executor`` and ``realtime_priority`` declared and read, every thread of the
    process under SCHED_FIFO where the OS allows it (before the driver's threads exist: each
    inherits it), and the hot executor. Raises :class:`ConfigError` naming a bad value."""
    declare(node, *PROCESS)
    realtime = spinning.go_realtime(node)
    return Process(spinning.make_executor(str(node.get_parameter("executor").value), node.context), realtime)


class Assembly:
    """A driver's nodes and executors: :meth:`build`, :meth:`start`, the caller spins :attr:`hot`,
    then :meth:`close`. ``joints``: the drives served (None: every drive); ``overrides``: parameters
    of the driver node that the entry point fixes (the demo's ``arm``); ``node``: the driver node
    the entry point made first to read the process's parameters (:func:`set_up`), served by
    :meth:`build` (else build makes one); ``failures``: the count of callback failures the driver node
    that build makes keeps (None: one of its own; a ``node`` given keeps its own)."""

    def __init__(self, driver: MotorDriver, hot: Executor, *, name: str = "rovercan_driver",
                 joints: Sequence[str] | None = None, context: Context | None = None,
                 overrides: Sequence[Parameter] = (), node: DriverNode | None = None,
                 failures: spinning.CallbackFailures | None = None) -> None:
        assert node is None or failures is None, "a driver node given keeps its own failure count"
        self.driver, self.hot = driver, hot
        self._failures = failures  # the driver node's count, where the caller keeps one (DriverNode's ``failures``)
        self._name, self._joints, self._overrides = name, joints, list(overrides)
        self._kwargs: dict[str, Any] = {} if context is None else {"context": context}
        self.node: DriverNode | None = node
        self.nodes: list[Node] = []  # every node made here, the hot ones first
        self.executors: dict[str, Executor] = {}  # node name -> its executor (the hot one included)
        self._threads: list[spinning.SpinThread] = []
        self.trajectories: dict[str, TrajectoryGroup] = {}  # the trajectory groups whose joints are all served
        self._log_handler: RclpyLogHandler | None = None
        self._started = False
        self._closed = False
        self._joined = False  # every thread of its own stopped at its close (its nodes may then be destroyed)

    # ------------------------------------------------------------------ steps
    def build(self) -> DriverNode:
        """Every ROS entity, added to its executor; nothing sent on the bus."""
        if self.node is None:
            node = self.node = DriverNode(self.driver, self._name, self._joints, parameter_overrides=self._overrides,
                                          failures=self._failures, **self._kwargs)
        else:
            node = self.node
            node.serve(self.driver, self._joints)
        if node not in self.nodes:
            self._own(node, self.hot)
        self._log_handler = bridge_core_logging(node)
        config = self.driver.config
        if config.drive_system is not None and self._joints is None and node.get_parameter("drive_system").value:
            self._own(DriveSystemNode.beside(node, self.driver, config, **self._kwargs), self.hot)  # its executor
        failures = node.callback_failures
        self._own(DriverStopsNode(self.driver, node.drives, failures=failures, **self._kwargs),
                  SingleThreadedExecutor(**self._kwargs))
        services = DriverServicesNode(self.driver, node.drives, failures=failures, **self._kwargs)
        self._own(services, MultiThreadedExecutor(num_threads=len(services.groups), **self._kwargs))
        self.trajectories = groups_of(config.trajectory_groups, node.drives)
        self._own(DriverActionsNode(self.driver, node.drives, trajectory_groups=self.trajectories, **self._kwargs),
                  SingleThreadedExecutor(**self._kwargs))
        self._supervise()
        heap.settle()  # what exists now lives as long as the process (a full collection stops
        # every thread, so it comes before the heartbeat starts)
        return node

    def _own(self, node: Node, executor: Executor) -> None:
        """``node`` on ``executor`` and this assembly's from now on: a build that fails after it
        (a parameter of a later node refused) still removes and destroys it at close."""
        executor.add_node(node)
        self.executors[node.get_name()] = executor
        self.nodes.append(node)

    def start(self, *, arm: bool = True) -> None:
        """The driver started (unless it was), the executors' threads, and, with ``arm``, every
        drive enabled when the node's ``arm`` parameter asks. Raises the driver's start error."""
        assert self.node is not None, "build() first"
        if not self._started:
            self._started = True
            self.driver.start()
        self.node.get_logger().info(
            f"{len(self.node.drives)} drive(s) on {len(self.driver.config.buses)} bus(es) booted; "
            + ("arming them" if arm and self.node.get_parameter("arm").value
               else f"not armed: {self.driver.motion_held or 'call /arm (std_srvs/Trigger)'}"))
        self._supervise()  # and what was made since build
        for n in self.nodes:
            executor = self.executors[n.get_name()]
            if executor is not self.hot and n.get_name() in THREADS:
                self._threads.append(spinning.SpinThread(executor, THREADS[n.get_name()], self.failures))
        if arm:
            self.node.arm_if_asked()

    @property
    def failures(self) -> spinning.CallbackFailures:
        """The callbacks of this process's nodes that raised (the driver node's /diagnostics says them);
        the caller's spin of :attr:`hot` counts there too (``runtime.spin_until(..., failures=...)``)."""
        assert self.node is not None, "build() first"
        return self.node.callback_failures

    def _supervise(self) -> None:
        """Every service, timer and subscription callback of the assembly's nodes supervised
        (nodes/process/spinning.py): an exception is logged once, counted, a service answers; none ends an executor."""
        for n in self.nodes:
            spinning.supervise(n, self.failures)

    def arm(self, joints: Collection[str] | None = None) -> list[str]:
        """Enable every served drive (or those of ``joints``), each whatever the others did; what
        failed, one line a drive."""
        assert self.node is not None
        failed = []
        for drive in self.node.drives.values():
            if joints is not None and drive.name not in joints:
                continue
            try:
                drive.enable()  # confirmed by the drive's statusword
            except RovercanError as err:
                failed.append(str(err))
        return failed

    def stop_drives(self) -> StopReport:
        """The driver's safe stop on the served drives; what was not confirmed (``lines`` empty: all safe)."""
        return self.driver.stop_report(None if self.node is None else self.node.drives.values())

    def close(self) -> None:
        """Drives safe (the driver closed), threads joined, nodes destroyed. Idempotent."""
        if self._closed:
            return
        self._closed = True
        teardown("assembly close", (self._close_groups, self.driver.close, self._join_threads, self._unbridge,
                                    self._remove_nodes))

    def _close_groups(self) -> None:
        for group in self.trajectories.values():  # no set-point of theirs after the driver's safe stop
            group.close()

    def _join_threads(self) -> None:
        self._joined = all([spin.stop(timeout_s=SERVICE_JOIN_S) for spin in self._threads])  # every one stopped

    def _unbridge(self) -> None:
        if self._log_handler is not None:
            unbridge(self._log_handler)

    def _remove_nodes(self) -> None:
        hot = self.hot
        for n in self.nodes:
            if n in hot.get_nodes():
                hot.remove_node(n)
        if self._joined:  # a thread still inside rclpy must not see its node destroyed under it
            for n in self.nodes:
                n.destroy_node()

    def layout(self) -> dict[str, tuple[str, str]]:
        """Node name -> (executor class, thread: ``hot`` or the thread's name): what the tests
        compare across entry points."""
        return {name: (type(executor).__name__, "hot" if executor is self.hot else THREADS[name])
                for name, executor in self.executors.items()}



def config_of(node: Node) -> RoverConfig:
    """The process's rover config, by its node's ``config`` (empty: ``$ROVERCAN_CONFIG`` where set,
    else the embedded default) and ``sim`` parameters: a launch that started the simulator for it
    (``sim:=true``) never reads ``$ROVERCAN_CONFIG`` (the deployed rover's real buses) and opens no
    bus but the simulator's (:func:`can_config.simulated_config`)."""
    path = str(node.get_parameter("config").value) or None
    if node.get_parameter("sim").value:
        return simulated_config(path, "this launch (sim:=true)")
    return load_config(path)


def assemble(name: str = "rovercan_driver", *, one_joint: bool = False, context: Context | None = None) -> Assembly:
    """An entry point's driver node with its parameters, the process set-up (:func:`set_up`), the
    driver of its ``config`` and their assembly built: nothing sent on the bus yet. ``one_joint``:
    the node serves the joint of its ``joint`` parameter only (motor_controller). Raises the
    :class:`RovercanError` of a bad parameter or config, with what was made undone."""
    kwargs: dict[str, Any] = {} if context is None else {"context": context}
    node = DriverNode(None, name, one_joint=one_joint, **kwargs)  # the node's name: a params file's values apply
    assembly = None
    try:
        declare(node, "config", "sim")
        process = set_up(node)
        joints = [node.joint()] if one_joint else None
        driver = MotorDriver(config_of(node))  # nothing sent yet
        assembly = Assembly(driver, process.hot, name=name, joints=joints, context=context, node=node)
        assembly.build()
    except BaseException:
        if assembly is not None:
            assembly.close()
        else:
            node.destroy_node()
        raise
    return assembly


def run(program: str, stop: StopSignal, *, name: str = "rovercan_driver", one_joint: bool = False) -> int:
    """An entry point's process: :func:`assemble`, the driver started, the hot executor spun on
    this thread until ``stop``, then the assembly closed."""
    assembly = None
    try:
        assembly = assemble(name, one_joint=one_joint)
        assembly.start()
        spinning.spin_until(assembly.hot, stop.event, failures=assembly.failures)
    except RovercanError as err:
        print(f"{program}: {err}", file=sys.stderr)
        return 2
    finally:
        try:
            if assembly is not None:
                assembly.close()  # each step runs; a step that raised is logged and raised here
        finally:
            rclpy.try_shutdown()
    return 0


__all__ = ["THREADS", "Assembly", "Process", "assemble", "run", "set_up"]

"""The emulator as one service: engine + socketcand server + simulated drives.

This is what ``rovercan sim`` runs and what tests and the demo start in-process::

    with SimService.from_config(load_config(), port=0) as sim:
        bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)

Owner: the thread that starts and closes it; the engine, the server and each channel's
simulator run on threads of their own, each owning its state.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from can_config import RoverConfig, load_drive_od
from can_config.config import GENERIC_EDS, SimModelConfig
from can_config.errors import ConfigError
from virtual_can.bus import VirtualBus
from virtual_can.engine import BusEngine
from virtual_can.server import DEFAULT_HOST, DEFAULT_PORT, SocketcandServer
from virtual_can.sim.drive import MotorParams, SimulatedDrive
from virtual_can.sim.runner import DEFAULT_TICK_S, DriveSimulator

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimDriveSpec:
    """One simulated drive: node id, EDS, channel and motor model."""

    node_id: int
    eds: Path = GENERIC_EDS
    channel: str = "can0"
    name: str | None = None
    counts_per_rev: int | None = None
    model: SimModelConfig = field(default_factory=SimModelConfig)

    def motor(self) -> MotorParams:
        return MotorParams.from_model(self.model, self.counts_per_rev)

    def drive(self) -> SimulatedDrive:
        """The simulated drive: its object dictionary, motor model and SYNC answer's lateness."""
        drive = SimulatedDrive(self.node_id, load_drive_od(self.eds, self.node_id), self.motor(), name=self.name)
        drive.faults.sync_delay_s = self.model.sync_answer_delay_s
        drive.faults.sync_jitter_s = self.model.sync_answer_jitter_s
        return drive


def specs_from_config(config: RoverConfig) -> list[SimDriveSpec]:
    """The simulator as a twin of the rover: one drive per configured drive, on its bus's channel."""
    return [SimDriveSpec(d.node_id, d.eds, config.bus(d.bus).channel, d.name, d.counts_per_rev, d.sim)
            for d in config.drives]


@dataclass(frozen=True)
class ServedPort:
    """One socketcand server of a config's twin: its TCP port, the channels (the buses of the
    config that name this port) and their simulated drives."""

    port: int
    channels: tuple[str, ...]
    specs: tuple[SimDriveSpec, ...]


def served_ports(config: RoverConfig) -> list[ServedPort]:
    """The servers a twin of ``config`` needs: one per distinct socketcand port of its buses (a
    bus without one is served on the default port), each with its buses' channels and drives."""
    specs = specs_from_config(config)
    by_port: dict[int, list[str]] = {}
    for bus in config.buses:
        port = int(bus.kwargs.get("port", DEFAULT_PORT))
        if bus.channel in by_port.setdefault(port, []):
            raise ConfigError(f"{config.source or 'config'}: two buses on port {port} share channel {bus.channel!r};"
                              " give each bus of one port a channel of its own")
        by_port[port].append(bus.channel)
    served = []
    for port, channels in by_port.items():
        mine = tuple(s for s, d in zip(specs, config.drives, strict=True)
                     if int(config.bus(d.bus).kwargs.get("port", DEFAULT_PORT)) == port)
        served.append(ServedPort(port, tuple(channels), mine))
    return served


def specs_for_count(n: int, eds: Path = GENERIC_EDS, channel: str = "can0") -> list[SimDriveSpec]:
    return [SimDriveSpec(i, eds, channel) for i in range(1, n + 1)]


class SimService:
    """Engine, socketcand server and one simulator thread per channel (``drive_models=False``:
    the server alone; the drives run elsewhere, as its clients: ``rovercan sim --drive-processes``)."""

    def __init__(self, specs: Sequence[SimDriveSpec], *, host: str = DEFAULT_HOST,
                 port: int = DEFAULT_PORT, wire_time: bool = False, bitrate: int = 1_000_000,
                 allow_remote: bool = False, tick_s: float = DEFAULT_TICK_S,
                 extra_channels: Sequence[str] = (), drive_models: bool = True) -> None:
        self.engine = BusEngine(bitrate=bitrate, wire_time=wire_time)
        channels = tuple(dict.fromkeys([*(s.channel for s in specs), *extra_channels])) or ("can0",)
        self.simulators: dict[str, DriveSimulator] = {}
        self._buses: list[VirtualBus] = []
        try:
            for channel in channels if drive_models else ():
                drives = [s.drive() for s in specs if s.channel == channel]
                bus = VirtualBus(channel, engine=self.engine)
                self._buses.append(bus)
                self.simulators[channel] = DriveSimulator(bus, drives, tick_s=tick_s, name=channel)
            self.server = SocketcandServer(self.engine, host, port, channels=channels,
                                           allow_remote=allow_remote)
        except BaseException:
            self._close_parts()
            raise
        for sim in self.simulators.values():
            sim.clock.on_bus_until = self.server.on_bus_until  # a silence is judged once its clients' frames are in
            sim.start()

    @classmethod
    def from_config(cls, config: RoverConfig, **kwargs: object) -> SimService:
        return cls(specs_from_config(config), **kwargs)  # type: ignore[arg-type]

    @property
    def host(self) -> str:
        return str(self.server.host)

    @property
    def port(self) -> int:
        return int(self.server.port)

    def simulator_for(self, node_id: int, channel: str | None = None) -> DriveSimulator:
        for name, sim in self.simulators.items():
            if (channel is None or name == channel) and node_id in sim.drives:
                return sim
        raise KeyError(f"no simulated drive {node_id}")

    def python_can_args(self, channel: str = "can0") -> str:
        return f"-i socketcand -c {channel} --bus-kwargs host={self.host} port={self.port}"

    def _close_parts(self) -> None:
        for sim in self.simulators.values():
            sim.close()
        for bus in self._buses:
            bus.shutdown()
        self.engine.close()

    def close(self) -> None:
        server = getattr(self, "server", None)
        if server is not None:
            server.close()
        self._close_parts()

    def __enter__(self) -> SimService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""The bus as ROS 2 messages on the bench: ``record FILE.mcap``, ``decode FILE -o OUT.mcap`` and the
live Foxglove view (``monitor --foxglove PORT``, also started by ``sim`` and ``launch``).

The messages are :class:`motor_driver.recording.busview.BusView`'s; this module opens the buses (every bus
of ``--config`` unless ``-c`` or bus arguments name one), reads them (a thread per bus, each
frame handed to the command's thread through a queue) and serves (:mod:`rovercan.bench.liveview`)
or writes what the view makes.
"""

from __future__ import annotations

import argparse
import logging
import math
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can

from can_config import load_config
from can_config.errors import BusLostError, ConfigError
from can_config.model import RoverConfig
from motor_driver.process.stop import StopSignal
from motor_driver.recording.busview import BusView, Frame, view_drives
from motor_driver.recording.files import iter_recording
from motor_driver.runtime.driver import open_bus as driver_open_bus
from rovercan.bench.common import connect_timeout, open_bus, receive

logger = logging.getLogger(__name__)

#: A bus's reader thread hands over at most this many frames not yet taken (a stalled writer
#: loses the newest, never the process's memory).
QUEUE_FRAMES = 100_000
#: The live view's server starts, or stops, within this long.
FOXGLOVE_START_S = 10.0


def open_buses(args: argparse.Namespace) -> list[tuple[str, can.BusABC]]:
    """(name, bus) of every bus a command reads: the one the bus arguments or ``-c`` name, else
    with ``--config`` every bus of it."""
    if getattr(args, "interface", None) is None and getattr(args, "config", None) and not getattr(args, "channel", None):
        config = load_config(args.config)
        opened: list[tuple[str, can.BusABC]] = []
        try:
            for bus_config in config.buses:
                opened.append((bus_config.name, driver_open_bus(bus_config.bus_kwargs(), connect_timeout(args))))
        except BaseException:
            for _, each in opened:
                each.shutdown()
            raise
        return opened
    one = open_bus(args)
    return [(str(getattr(args, "channel", None) or one.channel_info), one)]


def frame_of(msg: can.Message, bus: str) -> Frame:
    return (msg.timestamp or time.time(), bus, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
            msg.is_error_frame, msg.dlc, bytes(msg.data))


def read_buses(buses: list[tuple[str, can.BusABC]], stop: threading.Event, seconds: float = 0.0
               ) -> Iterator[tuple[str, can.Message]]:
    """Every frame of ``buses`` as it comes, until ``stop`` is set or ``seconds`` have passed; a
    bus lost ends it with :class:`BusLostError`. The buses are shut down at the end."""
    frames: queue.Queue[tuple[str, can.Message | BaseException]] = queue.Queue(QUEUE_FRAMES)
    done = threading.Event()

    def reader(name: str, bus: can.BusABC) -> None:
        try:
            while not done.is_set():
                msg = receive(bus, 0.2)
                if msg is not None:
                    try:
                        frames.put_nowait((name, msg))
                    except queue.Full:
                        logger.warning("%s: frames not taken in time; one dropped", name)
        except (BusLostError, can.CanError, OSError) as err:
            frames.put((name, err))

    threads = [threading.Thread(target=reader, args=item, daemon=True, name=f"rovercan-read-{item[0]}")
               for item in buses]
    for thread in threads:
        thread.start()
    end = time.monotonic() + seconds if seconds else math.inf
    try:
        while not stop.is_set() and time.monotonic() < end:
            try:
                name, item = frames.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise item
            yield name, item
    finally:
        done.set()
        for thread in threads:
            thread.join(timeout=2.0)
        for _, bus in buses:
            bus.shutdown()


def config_of(args: argparse.Namespace) -> RoverConfig | None:
    return load_config(args.config) if getattr(args, "config", None) else None


def record_mcap(args: argparse.Namespace) -> int:
    """``rovercan record FILE.mcap``: frames and, with --config, every drive decoded, with its units
    in the file's metadata."""
    from motor_driver.recording.mcap_out import UNITS_METADATA, McapSink, config_units_warning, units_metadata

    config = config_of(args)
    buses = open_buses(args)
    names = ", ".join(name for name, _ in buses)
    print(f"rovercan record: recording {names} to {args.file}", file=sys.stderr, flush=True)
    n = 0
    with StopSignal() as stop, McapSink(args.file, {"command": "rovercan record", "buses": names,
                                                      "config": str(args.config or "")}) as sink:
        view = BusView(view_drives(config) if config else [], sink)
        try:
            for name, msg in read_buses(buses, stop.event, args.seconds):
                view.feed(frame_of(msg, name))
                n += 1
        finally:
            view.finish()
            if config:
                sink.add_metadata(UNITS_METADATA, units_metadata(view))
    if config and (guessed := view.config_units()):
        print(config_units_warning("rovercan record", guessed), file=sys.stderr)
    print(f"rovercan record: {n} frames to {args.file}", file=sys.stderr)
    return 0


def recording_frames(path: str, config: RoverConfig | None) -> Iterator[Frame]:
    """A recording's frames, read as they come, each given its bus: a channel that names a bus of
    the config (its name or channel, or the number of its channel), else the config's first bus."""
    buses = config.buses if config else ()
    default = buses[0].name if buses else "can0"
    by_channel: dict[object, str] = {}
    for bus in buses:
        by_channel.update({bus.name: bus.name, bus.channel: bus.name})
        digits = "".join(c for c in bus.channel if c.isdigit())
        if digits:
            by_channel.setdefault(int(digits), bus.name)
    for msg in iter_recording(path):
        yield frame_of(msg, by_channel.get(msg.channel, default) if msg.channel is not None else default)


def mcap_recording(path: str) -> tuple[Iterator[Frame], dict[str, dict[tuple[int, int], int]]]:
    """The frames of an MCAP recording (its /can/frames, each on the bus it names) and the drives'
    unit objects its metadata holds (:data:`motor_driver.recording.mcap_out.UNITS_METADATA`)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from motor_driver.recording.busview import FRAMES_TOPIC
    from motor_driver.recording.mcap_out import UNITS_METADATA, recorded_units

    try:
        with open(path, "rb") as file:
            units: dict[str, dict[tuple[int, int], int]] = {}
            for record in make_reader(file).iter_metadata():
                if record.name == UNITS_METADATA:
                    units = recorded_units(record.metadata)
    except (OSError, McapError, ValueError) as err:
        raise ConfigError(f"{path}: not an MCAP file this can read ({err}); give a recording of `rovercan record"
                          " FILE.mcap`") from err

    def frames() -> Iterator[Frame]:
        with open(path, "rb") as file:
            reader = make_reader(file, decoder_factories=[DecoderFactory()])
            for _, _, _, m in reader.iter_decoded_messages(topics=[FRAMES_TOPIC]):
                yield (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.header.frame_id, m.id, m.is_extended,
                       m.is_rtr, m.is_error, m.dlc, bytes(m.data))

    return frames(), units


def decode_mcap(args: argparse.Namespace) -> int:
    """``rovercan decode FILE -o OUT.mcap``: the recording as ROS 2 messages; an MCAP recording's
    drives in the units its metadata holds."""
    from motor_driver.recording.mcap_out import config_units_warning, write_mcap

    if Path(args.output).suffix.lower() != ".mcap":
        raise ConfigError(f"-o {args.output}: decode writes .mcap files; name it OUT.mcap")
    config = config_of(args)
    if Path(args.file).suffix.lower() == ".mcap":
        frames, units = mcap_recording(args.file)
    else:
        frames, units = recording_frames(args.file, config), {}
    n, guessed = write_mcap(args.output, frames, config, {"command": "rovercan decode", "source": str(args.file),
                                                          "config": str(args.config or "")}, units)
    if guessed:
        print(config_units_warning("rovercan decode", guessed), file=sys.stderr)
    print(f"rovercan decode: {n} frames to {args.output}", file=sys.stderr)
    return 0


def _nowhere(topic: str, type_name: str, message: dict[str, Any], time_ns: int) -> None:
    """An emit that keeps nothing (a view asked only for its channels)."""


def serve_view(buses: list[tuple[str, can.BusABC]], config: RoverConfig | None, host: str, port: int,
               stop: threading.Event, seconds: float = 0.0, say: Callable[[str], None] | None = None) -> int:
    """Serve the view of ``buses`` until ``stop``; returns the frames seen."""
    try:
        from rovercan.bench.liveview import LiveView
    except ImportError as err:
        raise ConfigError(f"--foxglove needs {err.name}: pip install 'rovercan[cli]' (./dev setup does)") from err
    drives = view_drives(config) if config else []
    sink = LiveView(BusView(drives, _nowhere).channels(), host, port)
    view = BusView(drives, sink)
    if say:
        say(f"Foxglove WebSocket on ws://{host}:{sink.port}: {len(view.channels())} channels"
            f" ({', '.join(name for name, _ in buses)}); open it in Foxglove with the layout"
            " docs/foxglove/rover_drives.json")
    n = 0
    try:
        for name, msg in read_buses(buses, stop, seconds):
            view.feed(frame_of(msg, name))
            n += 1
    finally:
        sink.close()
    return n


def sim_buses(sims: list[Any], config: RoverConfig | None) -> list[tuple[str, can.BusABC]]:
    """A client bus on every channel the simulator servers (:class:`virtual_can.SimService`) serve,
    named as the config names it (else by its channel)."""
    def client(sim: Any, channel: str) -> can.BusABC:
        host = "127.0.0.1" if sim.host in ("0.0.0.0", "") else sim.host
        return can.Bus(interface="socketcand", channel=channel, host=host, port=sim.port)

    if config is None:
        return [(channel, client(sim, channel)) for sim in sims for channel in sim.simulators]
    opened: list[tuple[str, can.BusABC]] = []
    for bus in config.buses:
        serving = [sim for sim in sims if bus.channel in sim.simulators and (
            len(sims) == 1 or sim.port == bus.bus_kwargs().get("port"))]
        if serving:
            opened.append((bus.name, client(serving[0], bus.channel)))
    return opened


@contextmanager
def serve_sims_view(sims: list[Any], config_path: str | None, host: str, port: int) -> Iterator[None]:
    """``rovercan sim --foxglove PORT``: the live view of the simulator's own buses, served from a
    thread of its own while the block runs."""
    config = load_config(config_path) if config_path else None
    stop = threading.Event()
    started = threading.Event()

    def say(text: str) -> None:
        print(f"rovercan sim: {text}", flush=True)
        started.set()

    def run() -> None:
        try:
            serve_view(sim_buses(sims, config), config, host, port, stop, say=say)
        except Exception as err:  # the view must never take the simulator down
            logger.error("rovercan sim: the Foxglove view stopped: %s", err)
        finally:
            started.set()

    thread = threading.Thread(target=run, daemon=True, name="rovercan-foxglove")
    thread.start()
    started.wait(FOXGLOVE_START_S)
    try:
        yield
    finally:
        stop.set()
        thread.join(FOXGLOVE_START_S)


def monitor_foxglove(args: argparse.Namespace) -> int:
    """``rovercan monitor --foxglove PORT``: the live view instead of printed lines."""
    config = config_of(args)
    buses = open_buses(args)
    with StopSignal() as stop:
        n = serve_view(buses, config, args.foxglove_host, args.foxglove, stop.event, args.seconds,
                       lambda text: print(f"rovercan monitor: {text}", file=sys.stderr, flush=True))
    print(f"rovercan monitor: {n} frames", file=sys.stderr)
    return 0

"""An hour of the rover converted to MCAP (issue 54): ``python benchmarks/mcap_convert.py [--minutes N] [--json]``.

Generates N minutes (default 60) of the shipped rover (config/rover.yaml: six wheel drives on
can0 and can1), streamed to a recording as it is made, never held in memory: on each bus a SYNC
every 10 ms (the config's period) and, after it, every TPDO the driver maps for transmission on
SYNC, laid out by the driver's own PDO plan (:func:`motor_driver.protocol.pdo.plan_pdos`) and packed by its
codec, each drive on its own ramp; each drive's event TPDO (statusword, mode) once at the start.
Then converts it with the CLI in a child process (``rovercan decode FILE -o OUT.mcap --config
config/rover.yaml``) and reports its wall time, its peak RSS (``getrusage(RUSAGE_CHILDREN)``),
frames/s and the output's size; reads the MCAP back with the mcap reader and counts its messages
per channel against what was generated (exit 1 when they disagree).

``--format blf`` (default) or ``log`` (``candump -L`` text). Run it at two lengths to see that the
peak RSS does not grow with the recording's (docs/performance.md, "MCAP conversion").
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import can  # noqa: E402

from can_config import load_config  # noqa: E402
from can_config.eds import load_drive_od  # noqa: E402
from can_config.model import RoverConfig  # noqa: E402
from can_config.objects import OD, FunctionCode, OperationMode  # noqa: E402
from motor_driver.protocol.pdo import TT_SYNC, PdoMap, encode_rpdo, plan_pdos  # noqa: E402
from motor_driver.recording.busview import DIAGNOSTICS_TOPIC, FRAMES_TOPIC, JOINT_STATES_TOPIC, status_topic  # noqa: E402

ROVER = REPO / "config" / "rover.yaml"
T0 = 1_800_000_000.0
#: After its bus's SYNC, drive i of the config answers i x this later (its TPDOs back to back).
ANSWER_STEP_S = 0.0001
STATUS_ENABLED = 0x0637  # operation enabled, voltage enabled, remote, target reached


def drive_pdos(config: RoverConfig) -> list[tuple[str, tuple[PdoMap, ...], tuple[PdoMap, ...]]]:
    """(bus, its SYNC TPDOs, its other TPDOs) of every drive, as the driver maps them."""
    out = []
    for d in config.drives:
        tpdos = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id).tpdos
        out.append((d.bus, tuple(p for p in tpdos if p.trans_type == TT_SYNC),
                    tuple(p for p in tpdos if p.trans_type != TT_SYNC)))
    return out


def rover_messages(config: RoverConfig, cycles: int) -> Iterator[can.Message]:
    """``cycles`` SYNC periods of the rover, time-ordered, made as they are asked for."""
    drives = drive_pdos(config)
    channel = {bus.name: bus.name for bus in config.buses}
    period_s = min(bus.sync_period_s for bus in config.buses)

    def frame(t: float, bus: str, cob: int, data: bytes) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=cob, data=data, is_extended_id=False, channel=channel[bus])

    for bus, _, events in drives:  # the event TPDO (statusword, mode) once, as after enabling
        for pdo in events:
            values: dict[int, int] = {OD.STATUSWORD: STATUS_ENABLED, OD.MODES_OF_OPERATION_DISPLAY: OperationMode.CYCLIC_SYNC_POSITION}
            yield frame(T0 - period_s / 2, bus, pdo.cob_id, encode_rpdo(pdo, values))
    for k in range(cycles):
        t = T0 + k * period_s
        for name in channel:
            yield frame(t, name, FunctionCode.SYNC, b"")
        for i, (bus, sync_pdos, _) in enumerate(drives):
            values = {OD.POSITION_ACTUAL: k * 37 * (i + 1) - 5000, OD.VELOCITY_ACTUAL: 900 * (i + 1) - k % 1800,
                      OD.TORQUE_ACTUAL: k % 200 - 100, OD.STATUSWORD: STATUS_ENABLED}
            for j, pdo in enumerate(sync_pdos):
                # the same codec packs the driver's RPDOs and decodes its TPDOs (a PdoMap either way)
                yield frame(t + ANSWER_STEP_S * (i + 1) + ANSWER_STEP_S / 10 * j, bus, pdo.cob_id, encode_rpdo(pdo, values))


def write_recording(path: Path, config: RoverConfig, cycles: int) -> int:
    """The recording, streamed to ``path`` (.blf: bus i is channel i; .log: candump -L, bus names)."""
    n = 0
    with can.Logger(str(path)) as writer:
        blf = path.suffix == ".blf"
        index = {bus.name: i for i, bus in enumerate(config.buses)}
        for msg in rover_messages(config, cycles):
            if blf:
                msg.channel = index[str(msg.channel)]
            writer.on_message_received(msg)
            n += 1
    return n


def convert(recording: Path, out: Path, config: Path) -> tuple[float, float, int]:
    """(wall s, the child's peak RSS in MiB, frames it says it converted) of ``rovercan decode``."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "rovercan", "decode", str(recording), "-o", str(out),
                           "--config", str(config)], cwd=REPO, capture_output=True, text=True)
    wall_s = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"rovercan decode failed ({done.returncode}): {done.stderr.strip()}")
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # the only child: decode's
    said = done.stderr.strip().splitlines()[-1]  # "rovercan decode: N frames to OUT.mcap"
    return wall_s, peak_kib / 1024, int(said.split(": ")[1].split()[0])


def count_messages(path: Path) -> tuple[dict[str, int], dict[str, int]]:
    """Messages per topic, read one by one with the mcap reader, and as its summary says."""
    from mcap.reader import make_reader

    read: Counter[str] = Counter()
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for _, channel, _ in reader.iter_messages():
            read[channel.topic] += 1
    if summary is None or summary.statistics is None:
        raise SystemExit(f"{path}: no summary section (the writer did not finish it)")
    said = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    return dict(read), said


def problems(config: RoverConfig, counts: dict[str, int], said: dict[str, int], frames: int, cycles: int,
             converted: int) -> list[str]:
    """What disagrees between the MCAP and the generated recording (empty: nothing)."""
    seconds = cycles * min(bus.sync_period_s for bus in config.buses)
    # one JointState and one status per drive a cycle (the first cycle may be split: +1), a summary a second
    expected = {FRAMES_TOPIC: (frames, frames), JOINT_STATES_TOPIC: (cycles, cycles + 1),
                DIAGNOSTICS_TOPIC: (math.floor(seconds), math.ceil(seconds) + 1)}
    expected.update({status_topic(d.name): (cycles, cycles + 1) for d in config.drives})
    found = [f"rovercan decode said {converted} frames, {frames} were generated"] if converted != frames else []
    for topic, (low, high) in expected.items():
        if not low <= counts.get(topic, 0) <= high:
            found.append(f"{topic}: {counts.get(topic, 0)} messages, expected {low}..{high}")
    found += [f"channel {topic} not expected" for topic in counts if topic not in expected]
    if counts != said:
        found.append(f"the summary's counts {said} are not the messages read {counts}")
    return found


def measure(minutes: float, fmt: str = "blf", config_path: Path = ROVER, keep: Path | None = None) -> dict[str, Any]:
    """Generate, convert, verify; the figures (``problems`` empty when the MCAP is right)."""
    config = load_config(config_path)
    cycles = max(1, round(minutes * 60 / min(bus.sync_period_s for bus in config.buses)))
    with tempfile.TemporaryDirectory(prefix="mcap-convert-") as tmp:
        where = keep or Path(tmp)
        recording, out = where / f"rover.{fmt}", where / "rover.mcap"
        start = time.perf_counter()
        frames = write_recording(recording, config, cycles)
        generate_s = time.perf_counter() - start
        wall_s, peak_mib, converted = convert(recording, out, config_path)
        start = time.perf_counter()
        counts, said = count_messages(out)
        verify_s = time.perf_counter() - start
        return {
            "minutes": minutes, "format": fmt, "config": str(config_path.relative_to(REPO) if config_path.is_relative_to(REPO)
                                                              else config_path),
            "sync_cycles": cycles, "frames_generated": frames, "frames_converted": converted,
            "recording_mb": round(recording.stat().st_size / 1e6, 1), "generate_s": round(generate_s, 1),
            "convert_wall_s": round(wall_s, 1), "convert_peak_rss_mb": round(peak_mib, 1),
            "frames_per_s": round(frames / wall_s), "mcap_mb": round(out.stat().st_size / 1e6, 1),
            "mcap_messages": sum(counts.values()), "messages_per_channel": counts, "verify_s": round(verify_s, 1),
            "problems": problems(config, counts, said, frames, cycles, converted)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="length of the recording (default 60)")
    parser.add_argument("--format", choices=("blf", "log"), default="blf", help="blf (default) or log (candump -L)")
    parser.add_argument("--config", type=Path, default=ROVER, help="the rover (default config/rover.yaml)")
    parser.add_argument("--keep", type=Path, help="write the recording and the MCAP into this directory and keep them")
    parser.add_argument("--json", action="store_true", help="the figures as JSON")
    args = parser.parse_args()
    if not 0 < args.minutes <= 24 * 60:
        parser.error(f"--minutes {args.minutes}: give 0 < N <= 1440")
    result = measure(args.minutes, args.format, args.config.resolve(), args.keep)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{result['minutes']:g} min of {result['config']} ({result['frames_generated']:,} frames,"
              f" {result['recording_mb']} MB {args.format}) -> {result['mcap_mb']} MB MCAP in {result['convert_wall_s']} s:"
              f" {result['frames_per_s']:,} frames/s, peak RSS {result['convert_peak_rss_mb']} MiB")
        for topic, n in sorted(result["messages_per_channel"].items()):
            print(f"  {topic}: {n:,}")
    for problem in result["problems"]:
        print(f"mcap_convert: {problem}", file=sys.stderr)
    return 1 if result["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())

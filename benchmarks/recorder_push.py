"""The flight recorder's push alone, this checkout's ``motor_driver/recording/flight.py`` against
another's (a base commit's worktree), both loaded into one process and timed interleaved, so a busy
machine slows both alike: ``python benchmarks/recorder_push.py OTHER/motor_driver/recording/flight.py [ROUNDS]``.

Three states of a bus's ring, each received frames through the receive tap (as the batch read
hands them: a read of READ frames together where the tap has ``on_read``, else one call a frame)
or an RPDO as canopen's send hands it over: ``ordinary`` (5,000 frames/s stamped, the window full
by time: each push puts one old frame out), ``bound_received`` and ``bound_sent`` (stamped now, the
ring at its count bound, as in a babbling node's storm). CPU time of this thread, best of ROUNDS
(15) of 20,000 frames; prints ns a frame for each and their ratio (this checkout over the other) as JSON.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from can_config.config import RecorderConfig  # noqa: E402

CALLS = 20_000
DATA = bytearray(b"\x37\x06\x10\x27\x00\x00\x00\x00")
#: frames a batch read hands the tap at once (three rounds of a drive's three TPDOs and a SYNC)
READ = 10


def receiver(tap: Any) -> Callable[[Callable[[], float]], None]:
    """A read of READ frames stamped by ``stamp()`` into ``tap``: together (``on_read``) or a frame a call."""
    on_read = getattr(tap, "on_read", None)

    def together(stamp: Callable[[], float]) -> None:
        on_read([(0x181, DATA, stamp(), 0) for _ in range(READ)])

    def one_by_one(stamp: Callable[[], float]) -> None:
        for _ in range(READ):
            tap.on_frame(stamp(), 0x181, 0, DATA)
    return together if on_read is not None else one_by_one


def load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def pushes(flight: ModuleType, recorders: list[Any]) -> dict[str, Callable[[], None]]:
    def recorder() -> Any:
        rec = flight.FlightRecorder(RecorderConfig(dir=Path(tempfile.mkdtemp()), seconds=10.0, plot=False),
                                    {"w": ("can0", 1)}, {"can0": "can0"})
        recorders.append(rec)
        return rec

    ordinary, bound = recorder(), recorder()
    receive, clock = receiver(ordinary.listener("can0")), [1_000_000.0]

    def tick() -> float:
        clock[0] += 2e-4
        return clock[0]

    def ordinary_push() -> None:
        receive(tick)

    for _ in range(60_000 // READ):  # 12 s of it: the window full by time
        ordinary_push()
    bound_receive, now, rpdo = receiver(bound.listener("can0")), time.time, bytes(8)
    for _ in range((flight.frames_cap(flight.DEFAULT_BITRATE, 11.0) + 1000) // READ):  # at its count bound
        bound_receive(now)

    def sent() -> None:
        for _ in range(READ):
            bound.record_frame("can0", 0x201, rpdo)
    return {"ordinary": ordinary_push, "bound_received": lambda: bound_receive(now), "bound_sent": sent}


def main() -> int:
    other = Path(sys.argv[1])
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 15
    recorders: list[Any] = []
    sides = {"this": pushes(load("flight_this", REPO / "motor_driver" / "recording" / "flight.py"), recorders),
             "other": pushes(load("flight_other", other), recorders)}
    timed = [(side, kind, fn) for side, fns in sides.items() for kind, fn in fns.items()]
    best = {(side, kind): float("inf") for side, kind, _ in timed}
    for _ in range(rounds):
        for side, kind, fn in timed:
            t0 = time.thread_time()
            for _ in range(CALLS // READ):
                fn()
            best[side, kind] = min(best[side, kind], (time.thread_time() - t0) / CALLS * 1e9)
    for rec in recorders:
        rec.close()
    print(json.dumps({kind: {"this_ns": round(best["this", kind]), "other_ns": round(best["other", kind]),
                             "ratio": round(best["this", kind] / best["other", kind], 3)} for kind in sides["this"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

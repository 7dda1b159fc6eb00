"""Long-running processes (the driver nodes, the simulator) settle their heap once they are up.

CPython's garbage collector stops every thread of the process for a full collection, and a
full collection walks every container object alive. Once a node is built, most of those
(rclpy, the canopen object dictionaries, the parsed EDS files: about 50,000 in the six-wheel
driver) live as long as the process, yet each full collection walked them again: measured in
the six-drive stack run (benchmarks/stack_run.py), one took 70 ms, and the driver's heartbeat,
which the drives watch with a 150 ms consumer time, went out 110 ms late. :func:`settle` moves
them out of the collector's sight (``gc.freeze``); later garbage is collected as before. A
frozen object that is dropped later is still freed by its reference count; only a reference
cycle among frozen objects would stay (start-up objects that live as long as the process).
"""

from __future__ import annotations

import gc
import logging

logger = logging.getLogger(__name__)


def settle() -> int:
    """Collect the start-up garbage, then freeze what is left; returns the objects frozen.
    Call once the process is built and before its real-time work; calling again freezes what
    was made since."""
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    logger.debug("heap settled: %d objects frozen out of the garbage collector's sight", frozen)
    return frozen

"""Real-time scheduling where timing is the product (the emulator's SYNC timer, the driver's
process): where the OS allows it.

A Linux thread under ``SCHED_FIFO`` runs the moment it is ready, ahead of every ordinary
(``SCHED_OTHER``) thread on its core; a timed wait wakes it within tens of microseconds however
busy the machine is. That is what the kernel's own timers give a real socketcand daemon's
broadcast manager. It needs ``CAP_SYS_NICE`` (root, or ``setcap cap_sys_nice+ep`` on the
interpreter, or an ``rtprio`` limit in ``/etc/security/limits.conf``); without it the thread stays
ordinary and says so once in the log. ``ROVERCAN_REALTIME=0`` turns it off (to compare).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

logger = logging.getLogger(__name__)

#: Above ordinary threads, below the kernel's own (threaded interrupts run at 50).
REALTIME_PRIORITY = 10
#: A driver process's threads (the nodes' ``realtime_priority``, the demo's ``--realtime-priority``).
DRIVER_PRIORITY = 20
#: What stands in for the rover's hardware: the simulated drives' runner, the bus server's threads
#: and its broadcast manager's timer. Below the driver's, so it never takes the driver's turn; above
#: real-time work of lesser weight (a CI run's other tests, a robot's bursts at 10), which starved
#: an ordinary simulator until its drives took the host for lost (docs/simulator.md).
SIM_PRIORITY = 15
ENV_SWITCH = "ROVERCAN_REALTIME"


def _may_try(what: str) -> bool:
    """Real-time scheduling is neither switched off (ROVERCAN_REALTIME=0) nor missing from the OS."""
    if os.environ.get(ENV_SWITCH, "1") == "0":
        logger.info("%s: real-time scheduling off (%s=0)", what, ENV_SWITCH)
        return False
    if not hasattr(os, "sched_setscheduler"):
        logger.info("%s: this OS has no SCHED_FIFO; ordinary scheduling", what)
        return False
    return True


def _set_fifo(what: str, tasks: Callable[[], Iterable[int]], priority: int, *, skip_ended: bool,
              refused: tuple[int, str], done: str) -> bool:
    """Each Linux task ``tasks()`` lists under ``SCHED_FIFO`` at ``priority``, said in the log
    (``done``, or at ``refused``'s level its text with the reason); True if they all are.
    ``skip_ended``: a task that ended meanwhile is passed over (a thread of this process), not a
    refusal (a pid someone asked for)."""
    try:
        for tid in tasks():
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            except ProcessLookupError:
                if not skip_ended:
                    raise
    except OSError as err:
        level, text = refused
        logger.log(level, "%s: " + text, what, err)
        return False
    logger.info("%s: " + done, what, priority)
    return True


def make_thread_realtime(what: str, priority: int = REALTIME_PRIORITY, *, pid: int = 0) -> bool:
    """Put the calling thread (or the single-threaded process ``pid``) under ``SCHED_FIFO`` at
    ``priority``; True if it now is. A thread only: the other threads of the process keep their
    scheduling."""
    return _may_try(what) and _set_fifo(
        what, lambda: [pid], priority, skip_ended=False, done="SCHED_FIFO priority %d",  # 0: this thread
        refused=(logging.INFO, "an ordinary thread: real-time scheduling refused (%s); give the interpreter"
                               " CAP_SYS_NICE or an rtprio limit for a steadier period on a busy machine"))


def make_process_realtime(what: str, priority: int) -> bool:
    """Every thread of this process under ``SCHED_FIFO`` at ``priority``, and so every thread it
    starts later (a new thread inherits its creator's scheduling); True if so. A process it starts
    inherits it too: the thread that starts one that must not (a plot helper) does it inside
    :func:`ordinary_thread`.

    On a busy machine an ordinary thread that wakes for a frame or a command waits for a core
    behind whatever runs there: the six-drive stack run's command latency p99 was 2.9 ms with the
    driver's threads ordinary and 1.2-1.6 ms with them under SCHED_FIFO (docs/performance.md)."""
    return _may_try(what) and os.path.isdir("/proc/self/task") and _set_fifo(
        what, lambda: sorted(int(t) for t in os.listdir("/proc/self/task")), priority, skip_ended=True,
        done="every thread under SCHED_FIFO priority %d",
        refused=(logging.WARNING, "ordinary scheduling: SCHED_FIFO refused (%s); give the interpreter CAP_SYS_NICE"
                                  " or an rtprio limit (docs/deployment.md) for a steady latency on a busy machine"))


_sim_refusal_said = False  # written under _sim_refusal_lock, by whichever thread is refused first
_sim_refusal_lock = threading.Lock()


def ensure_thread_realtime(what: str, priority: int = SIM_PRIORITY) -> bool:
    """The calling thread under ``SCHED_FIFO`` at ``priority`` at least (as it is when it inherited
    that from its creator: then nothing is said); True if so. A refusal is said once per process,
    as a warning: the simulator's runner and the bus server's threads each ask, and on a machine
    that refuses them all one line says what a busy machine will do to them."""
    global _sim_refusal_said
    if hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) == os.SCHED_FIFO \
            and os.sched_getparam(0).sched_priority >= priority:
        return True
    if not _may_try(what):
        return False
    with _sim_refusal_lock:
        level = logging.DEBUG if _sim_refusal_said else logging.WARNING
        done = _set_fifo(what, lambda: [0], priority, skip_ended=False, done="SCHED_FIFO priority %d", refused=(
            level, f"the simulated drives and the bus server run at ordinary scheduling: SCHED_FIFO {priority}"
                   " refused (%s); on a busy machine their frames are then handled late (their bus stamps still"
                   " decide a heartbeat's verdict); give the interpreter CAP_SYS_NICE or an rtprio limit"
                   " (docs/simulator.md)"))
        _sim_refusal_said = _sim_refusal_said or not done
    return done


@contextmanager
def ordinary_thread() -> Iterator[None]:
    """The calling thread under ordinary scheduling (always allowed) for the block, then back to
    what it was: a process started inside starts ordinary (a child takes the scheduling of the
    thread that forked it), and the thread is real-time again after."""
    if not hasattr(os, "sched_setscheduler"):
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError as err:
        logger.debug("ordinary scheduling: %s", err)
    try:
        yield
    finally:
        try:
            os.sched_setscheduler(0, policy, param)
        except OSError as err:  # it was allowed before; if no longer, this thread stays ordinary
            logger.debug("scheduling not restored: %s", err)


def fifo_thread_count(pid: int, *, children: bool = False) -> int:
    """Threads of process ``pid`` (and, with ``children``, of its child processes: the bus
    server's timer is one) under SCHED_FIFO (/proc/PID/task/TID/stat, field 41); 0 where there is
    no /proc."""
    from pathlib import Path

    count = 0
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            count += int((task / "stat").read_text().rsplit(")", 1)[1].split()[38]) == os.SCHED_FIFO
            kids = (task / "children").read_text().split() if children else []
        except OSError:
            continue  # the thread ended meanwhile
        count += sum(fifo_thread_count(int(kid), children=True) for kid in kids)
    return count

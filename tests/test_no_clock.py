"""No clock in a test (issue 40): a shared runner is slow at random, so a test checks order and
outcome and waits on conditions; timing claims live in the benchmarks. An AST scan of tests/:

- a ``time.sleep`` outside any loop stands for "long enough": a bare wait. A sleep inside a
  ``while``/``for`` loop paces a stream or a poll whose condition is the loop's (allowed).
- an ``assert`` that compares a measured duration (``time.monotonic()``/``time.time()``/
  ``time.perf_counter()`` minus something, or a name assigned from one) with a constant under
  1 s is a wall-clock bound. A deadline of a second or more only catches a hang (allowed).
- a loop that runs for a span of the wall clock (``while time.monotonic() < t_end``, leaving on
  nothing else), or a call of a function of the file that runs one, followed by an assertion:
  publishing /cmd_vel for 2 s and then expecting the wheels at speed fails when the machine is
  busy. Loop until the outcome instead (``publish_until``, ``wait_for``), with a hang bound.
- a connect retried in a loop on ``OSError``/``ConnectionRefusedError``: a deadline decides whether
  the listener came up in time. Wait for the server to say it listens, then connect once.
- commands paced to a wall-clock schedule (``start + (i + 1) * period`` and a sleep) with no
  ``except CommandRejected``: a starved sender finds the drive's channel held by the work its
  previous command started, and that refusal (nothing sent) is an outcome to count, not a failure.

The scan is also run on broken snippets, so it can fail.
"""

from __future__ import annotations

import ast
from pathlib import Path

from .conftest import REPO

CLOCKS = {"monotonic", "time", "perf_counter", "monotonic_ns", "perf_counter_ns"}
#: Reasons shared by several entries below.
RAW_HOLD = ("the socketcand server holds a new raw client's frames for RAWMODE_HOLD_S unless it speaks, and"
            " python-can's client never speaks: the sleep outlasts a rule of the server, it waits for no outcome")
#: Bare sleeps not turned into waits on a condition, by test function, each with its reason: a
#: rule of another part outlasted, or a moment that is the test's input.
#: A new one anywhere fails this check, and so does an entry whose function has no bare sleep
#: left (test_the_allow_list_holds_no_stale_entry). Shrink it; never grow it.
ALLOWED_BARE_SLEEPS: dict[str, str] = {
    "conftest.py::listener_factory":
        RAW_HOLD,
    "test_bench_manners.py::test_ctrl_c_at_any_moment_gives_one_line_and_no_traceback":
        ("the moment of the Ctrl-C is the test's input (generated moments after the start), not a wait for "
         'anything'),
    "test_host_loss.py::run_and_stop":
        ("the host process runs past the drives' consumer time before it is stopped: the span is the input (a "
         "host that kept beating that long), the drives' stop is judged on the bus"),
    "test_host_loss.py::watching":
        RAW_HOLD,
    "test_hostile_sdo.py::__init__":
        RAW_HOLD,
    "test_hostile_sdo.py::test_fuzzed_answers_never_raise_outside_the_tree":
        RAW_HOLD,
    "test_kernel_tier.py::test_the_interface_down_then_up_stops_commands_and_configures_again_unarmed":
        ("the interface stays down 2 s once the driver said the bus lost: the span is the input (a link down"
         " for a while, retried through), the verdict is what follows (configured again, not armed)"),
    "test_reliability.py::test_random_frames_never_crash_the_driver":
        ("paces generated bursts so that the driver's threads run between them (load shaping, no verdict "
         'follows it)'),
    "test_ros_interface.py::test_cmd_vel_beyond_every_limit_is_scaled_whole_and_nothing_moves_after_it_stops":
        RAW_HOLD + ("; and 10 s of the bus after /cmd_vel stopped: the span is the input (the wheels stay stopped"
                    " that long), judged on every TPDO of it read back from the listeners' queues"),
    "test_second_master.py::test_a_drive_another_master_left_enabled_is_disabled_when_configured_again":
        RAW_HOLD,
    "test_second_master.py::test_an_sdo_write_by_another_client_stops_and_marks_the_drive_but_a_read_does_not":
        RAW_HOLD,
    "test_server.py::test_a_client_with_a_cyclic_job_outlives_the_handshake_timeout":
        ("outlasts the server's handshake timeout (the test's own short setting), the rule under test; the "
         "client's staying connected after it is the verdict"),
    "test_server_slots.py::test_idle_hostile_connections_give_way_to_a_well_behaved_client":
        ('idle_s is the input: a connection idle that long is what the server must drop (the test sets idle_s '
         'itself)'),
}


def _is_call_to(node: ast.AST, names: set[str], module: str = "time") -> bool:
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in names
            and isinstance(node.func.value, ast.Name) and node.func.value.id == module)


def _measures_time(node: ast.AST, timed: set[str]) -> bool:
    """An expression that is a duration measured by a clock: clock() - x, a name holding one, or
    max/min/sum of such (the worst of many)."""
    if isinstance(node, ast.Name):
        return node.id in timed
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub):
        return _is_call_to(node.left, CLOCKS) or _measures_time(node.left, timed)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("max", "min", "sum"):
        return any(_measures_time(arg, timed) for arg in node.args)
    return False


ARITHMETIC = {ast.Add: float.__add__, ast.Sub: float.__sub__, ast.Mult: float.__mul__, ast.Div: float.__truediv__}


def _constant(node: ast.AST) -> float | None:
    """A number written in the test: a literal, or arithmetic of literals (``0.35 + 0.1 + 0.05``)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.BinOp) and type(node.op) in ARITHMETIC:
        left, right = _constant(node.left), _constant(node.right)
        if left is not None and right is not None and not (isinstance(node.op, ast.Div) and right == 0):
            return ARITHMETIC[type(node.op)](left, right)
    return None


class Scan(ast.NodeVisitor):
    def __init__(self, name: str) -> None:
        self.name = name
        self.loops = 0
        self.function = ""
        self.timed: set[str] = set()
        self.problems: list[str] = []

    def _loop(self, node: ast.While | ast.For | ast.AsyncFor) -> None:
        self.loops += 1
        self.generic_visit(node)
        self.loops -= 1

    visit_While = visit_For = visit_AsyncFor = _loop  # noqa: N815 - ast.NodeVisitor's names

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        loops, self.loops = self.loops, 0  # a function defined in a loop runs when called, not per turn
        outer, self.function = self.function, self.function or node.name
        self.generic_visit(node)
        self.loops, self.function = loops, outer

    def visit_Assign(self, node: ast.Assign) -> None:
        if _measures_time(node.value, self.timed):
            self.timed |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        if _is_call_to(node, {"sleep"}) and not self.loops and f"{self.name}::{self.function}" not in ALLOWED_BARE_SLEEPS:
            self.problems.append(f"{self.name}:{node.lineno} ({self.function}): a bare time.sleep (wait for a"
                                 " condition instead)")
        self.generic_visit(node)

    def visit_Assert(self, node: ast.Assert) -> None:
        """An upper bound under 1 s on a measured duration (a slow runner breaks it; a lower bound,
        "at least this late", it cannot)."""
        for compare in (n for n in ast.walk(node.test) if isinstance(n, ast.Compare)):
            sides = [compare.left, *compare.comparators]
            for left, op, right in zip(sides[:-1], compare.ops, sides[1:], strict=True):
                below = (isinstance(op, (ast.Lt, ast.LtE)) and _measures_time(left, self.timed) and _constant(right))
                above = (isinstance(op, (ast.Gt, ast.GtE)) and _measures_time(right, self.timed) and _constant(left))
                bound = _constant(right) if below else _constant(left) if above else None
                if bound is not None and bound < 1.0:
                    self.problems.append(f"{self.name}:{node.lineno}: asserts a duration under {bound:g} s"
                                         " (a timing claim: a benchmark's, not a test's)")
        self.generic_visit(node)


def _walk_here(node: ast.AST) -> list[ast.AST]:
    """``node`` and what is under it, but not inside a function or class defined there (that runs
    when called, not here)."""
    found, todo = [], [node]
    while todo:
        item = todo.pop()
        found.append(item)
        todo += [child for child in ast.iter_child_nodes(item)
                 if not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef))]
    return found


def _clock_names(tree: ast.AST) -> set[str]:
    """Names given a reading of the clock (``start = time.monotonic()``, ``t_end = time.monotonic() + 2``),
    alone or in a tuple assignment."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Assign):
            continue
        pairs: list[tuple[ast.AST, ast.AST]] = []
        for target in node.targets:
            if isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                pairs += zip(target.elts, node.value.elts, strict=False)
            else:
                pairs.append((target, node.value))
        for target, value in pairs:
            if isinstance(target, ast.Name) and any(_is_call_to(n, CLOCKS) for n in ast.walk(value)):
                names.add(target.id)
    return names


def _runs_a_span(loop: ast.AST, clocks: set[str]) -> bool:
    """A ``while`` that runs until the clock reaches a time (``while time.monotonic() < t_end``) and
    leaves on nothing else: it lasts a span of the wall clock, whatever happened in it."""
    if not isinstance(loop, ast.While) or not isinstance(loop.test, ast.Compare):
        return False
    sides = [loop.test.left, *loop.test.comparators]
    reads_clock = any(_is_call_to(side, CLOCKS) for side in sides)
    until = any((isinstance(side, ast.Name) and side.id in clocks) or isinstance(side, ast.BinOp) for side in sides)
    leaves = any(isinstance(n, (ast.Break, ast.Return, ast.Raise)) for stmt in loop.body for n in _walk_here(stmt))
    return reads_clock and until and not leaves


def _called_name(node: ast.AST) -> str:
    if isinstance(node, ast.Call):
        func = node.func
        return func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    return ""


def _span_then_assert(tree: ast.AST, name: str) -> list[str]:
    """A loop over a span of the wall clock (or a call of a function of the file that runs one),
    followed by an assertion on what it reached: on a crowded machine the span passes with the
    work undone (publishing /cmd_vel for 2 s, then expecting the wheels at speed)."""
    clocks = _clock_names(tree)
    spanning = {f.name for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                and any(_runs_a_span(n, clocks) for stmt in f.body for n in _walk_here(stmt))}
    problems = []
    for block in (getattr(n, field, None) for n in ast.walk(tree) for field in ("body", "orelse", "finalbody")):
        if not isinstance(block, list):
            continue
        for i, stmt in enumerate(block):
            span = _runs_a_span(stmt, clocks) or (isinstance(stmt, ast.Expr) and _called_name(stmt.value) in spanning)
            if span and any(isinstance(n, ast.Assert) for later in block[i + 1:] for n in _walk_here(later)):
                problems.append(f"{name}:{stmt.lineno}: a loop over a span of the wall clock, then an assertion on"
                                " what it reached (loop until the outcome, with a hang bound)")
    return problems


CONNECT_ERRORS = {"OSError", "ConnectionRefusedError", "ConnectionError"}


def _connect_retried(tree: ast.AST, name: str) -> list[str]:
    """A connect tried again and again until the listener happens to be up (a deadline of the
    wall clock decides whether it was up in time): wait for the server to say it listens (its
    output line, a ready event, a port it reports) and connect once."""
    problems = []
    for loop in (n for n in ast.walk(tree) if isinstance(n, (ast.While, ast.For, ast.AsyncFor))):
        for node in (n for stmt in loop.body for n in _walk_here(stmt)):
            if not isinstance(node, ast.Try):
                continue
            caught = {n.id for h in node.handlers if h.type is not None for n in ast.walk(h.type) if isinstance(n, ast.Name)}
            connects = any("connect" in _called_name(n).lower() for stmt in node.body for n in _walk_here(stmt))
            if connects and caught & CONNECT_ERRORS:
                problems.append(f"{name}:{node.lineno}: a connect retried until the listener is up (wait for it to"
                                " say it listens, then connect once)")
    return problems


def _schedule_without_refusals(tree: ast.AST, name: str) -> list[str]:
    """A stream of commands paced to a wall-clock schedule (``start + (i + 1) * period``) that takes
    no refusal: a sender starved past its slot finds the drive's channel held by the work the
    previous command started, and the refusal (CommandRejected, nothing sent) is an outcome."""
    starts = {n.targets[0].id for n in ast.walk(tree) if isinstance(n, ast.Assign) and len(n.targets) == 1
              and isinstance(n.targets[0], ast.Name) and _is_call_to(n.value, CLOCKS)}
    problems = []
    for loop in (n for n in ast.walk(tree) if isinstance(n, (ast.While, ast.For))):
        inside = [n for stmt in loop.body for n in _walk_here(stmt)]
        paced = any(isinstance(n, ast.BinOp) and isinstance(n.op, ast.Add) and isinstance(n.left, ast.Name)
                    and n.left.id in starts and isinstance(n.right, ast.BinOp) and isinstance(n.right.op, ast.Mult)
                    for n in inside)
        paced = paced and any(_is_call_to(n, {"sleep"}) for n in inside)
        takes = any(isinstance(n, ast.ExceptHandler) and n.type is not None
                    and any(isinstance(t, ast.Name) and t.id == "CommandRejected" for t in ast.walk(n.type)) for n in inside)
        if paced and not takes:
            problems.append(f"{name}:{loop.lineno}: commands paced to a wall-clock schedule with no refusal taken"
                            " (a starved sender's command is refused: count it, send the next)")
    return problems


def scan(source: str, name: str) -> list[str]:
    visitor = Scan(name)
    tree = ast.parse(source)
    visitor.visit(tree)
    return visitor.problems + _span_then_assert(tree, name) + _connect_retried(tree, name) + \
        _schedule_without_refusals(tree, name)


def check_snippets(broken: str, lines: list[str], fine: str) -> list[str]:
    """The scan flags ``broken`` at exactly ``lines`` and ``fine`` (the same steps done right)
    nowhere; returns what it said of ``broken``."""
    found = scan(broken, "broken.py")
    assert [p.split(":", 2)[1].split(" ")[0] for p in found] == lines, found
    assert scan(fine, "fine.py") == []
    return found


def test_no_test_waits_on_a_bare_sleep_or_asserts_a_short_duration() -> None:
    problems = [p for path in sorted((REPO / "tests").glob("*.py")) for p in scan(path.read_text(), path.name)]
    assert problems == [], "\n".join(problems)


def test_the_allow_list_holds_no_stale_entry() -> None:
    """Every allowed function still has a bare sleep (one converted leaves the list), and each
    entry says why it stays."""
    class Every(Scan):
        def visit_Call(self, node: ast.Call) -> None:
            if _is_call_to(node, {"sleep"}) and not self.loops:
                self.problems.append(f"{self.name}::{self.function}")
            ast.NodeVisitor.generic_visit(self, node)

    found = set()
    for path in sorted((REPO / "tests").glob("*.py")):
        visitor = Every(path.name)
        visitor.visit(ast.parse(path.read_text()))
        found |= set(visitor.problems)
    assert not set(ALLOWED_BARE_SLEEPS) - found, sorted(set(ALLOWED_BARE_SLEEPS) - found)
    assert all(len(reason) > 20 for reason in ALLOWED_BARE_SLEEPS.values())


def test_the_scan_finds_a_bare_sleep_and_a_clock_assert() -> None:
    broken = ("import time\n"
              "def test_x():\n"
              "    start = time.monotonic()\n"
              "    time.sleep(0.3)\n"
              "    took = time.monotonic() - start\n"
              "    assert took < 0.05\n"
              "    assert time.monotonic() - start <= 0.5\n"
              "    worst = max(0.0, time.perf_counter() - start)\n"
              "    assert 0.005 > worst\n"
              "    assert time.monotonic() - start < 0.35 + 0.1 + 5 * 0.01\n")
    fine = ("import time\n"
            "def test_y(ready):\n"
            "    start = time.monotonic()\n"
            "    while not ready():\n"
            "        time.sleep(0.01)\n"
            "    assert time.monotonic() - start < 30.0\n"
            "    assert time.monotonic() - start >= 0.18\n")
    check_snippets(broken, ["4", "6", "7", "9", "10"], fine)


def test_the_scan_finds_a_span_then_an_assertion_a_connect_retried_and_a_schedule_without_refusals() -> None:
    broken = ("import time, socket\n"
              "def test_x(cmd, wheel):\n"
              "    t_end = time.monotonic() + 2.0\n"
              "    while time.monotonic() < t_end:\n"
              "        cmd.publish()\n"
              "        time.sleep(0.05)\n"
              "    assert wheel.speed() == 2.5\n"
              "    def drive_for(seconds):\n"
              "        until = time.monotonic() + seconds\n"
              "        while time.monotonic() < until:\n"
              "            cmd.publish()\n"
              "    drive_for(1.5)\n"
              "    assert wheel.speed() > 100\n"
              "    while True:\n"
              "        try:\n"
              "            sock = socket.create_connection(('127.0.0.1', 1))\n"
              "        except ConnectionRefusedError:\n"
              "            time.sleep(0.1)\n"
              "    start = time.monotonic()\n"
              "    for i in range(1000):\n"
              "        wheel.move_to(i)\n"
              "        time.sleep(max(0.0, start + (i + 1) * 0.001 - time.monotonic()))\n")
    fine = ("import time, socket\n"
            "from can_config.errors import CommandRejected\n"
            "def test_y(cmd, wheel, said):\n"
            "    deadline = time.monotonic() + 30.0\n"
            "    while wheel.speed() < 2.5:\n"
            "        assert time.monotonic() < deadline\n"
            "        cmd.publish()\n"
            "        time.sleep(0.05)\n"
            "    assert wheel.speed() == 2.5\n"
            "    while time.monotonic() < deadline:\n"
            "        if wheel.stopped():\n"
            "            break\n"
            "    assert wheel.stopped()\n"
            "    said.wait('listens')\n"
            "    sock = socket.create_connection(('127.0.0.1', 1))\n"
            "    start = time.monotonic()\n"
            "    for i in range(1000):\n"
            "        try:\n"
            "            wheel.move_to(i)\n"
            "        except CommandRejected:\n"
            "            pass\n"
            "        time.sleep(max(0.0, start + (i + 1) * 0.001 - time.monotonic()))\n"
            "    t0 = time.time()\n"
            "    frames = [t0 + i * 1e-4 for i in range(10)]\n")
    found = check_snippets(broken, ["4", "12", "15", "20"], fine)
    assert ["span" in found[0], "span" in found[1], "connect" in found[2], "schedule" in found[3]] == [True] * 4


def test_the_kernel_tier_and_every_tier_are_scanned() -> None:
    assert Path(REPO / "tests" / "test_kernel_tier.py").is_file()

"""run.py's reference of a node made of rclpy and the canopen library, in parts (the bare path plus
the canopen library's state run, over its same work; benchmarks/verdicts.py, pure, no ROS): none
where a part is missing, or where the bare path lost its commands on the way (a starved run costs
less and would lower the figure unsaid); and the stack run's thread names read from py-spy's dump,
the thread holding the interpreter among them."""

from __future__ import annotations

import sys

import pytest

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
from verdicts import rclpy_canopen_ratio


def test_the_parts_over_the_same_work() -> None:
    assert rclpy_canopen_ratio(0.286, 1.0, 0.198, 0.326) == 1.48
    assert rclpy_canopen_ratio(0.066, 0.95, 0.070, 0.119) == 1.14


@pytest.mark.parametrize("delivered", [0.949, 0.5, 0.0, None])
def test_no_figure_from_a_bare_path_that_lost_its_commands(delivered: float | None) -> None:
    assert rclpy_canopen_ratio(0.286, delivered, 0.198, 0.326) is None


@pytest.mark.parametrize("bare, state, base", [(None, 0.198, 0.326), (0.286, None, 0.326), (0.286, 0.198, None),
                                                (0.286, 0.198, 0.0)])
def test_no_figure_without_every_part(bare: float | None, state: float | None, base: float | None) -> None:
    assert rclpy_canopen_ratio(bare, 1.0, state, base) is None


def test_every_thread_of_a_py_spy_dump_is_named_the_one_holding_the_interpreter_too() -> None:
    from stack_run import thread_names_in

    dump = ('Process 17986: python threads2.py\nPython v3.11.7\n\nThread 17986 (idle): "MainThread"\n'
            '    <module> (threads2.py:5)\nThread 17988 (active+gil): "spinner"\n    spin (threads2.py:3)\n'
            'Thread 17990 (active): "Notifier for bus \\"socketcand on can0\\""\n')
    assert thread_names_in(dump) == {17986: "MainThread", 17988: "spinner",
                                     17990: 'Notifier for bus \\"socketcand on can0\\"'}

"""The batch's progress: the estimate of the time left and where the bar may appear
(:class:`benchmarks.batch.Progress`)."""

from __future__ import annotations

import io

import pytest

from benchmarks.batch import Progress, time_left


def test_nothing_is_estimated_before_a_task_has_finished():
    assert time_left(10.0, [], 3, 4, [(True, 5.0)]) is None


def test_the_estimate_weighs_cold_and_warm_tasks_apart():
    # Two cold tasks of 30 s and two warm ones of 2 s in 34 s of elapsed time on two
    # workers (64 s of task time): c = 30, w = 2, one cold and five warm left,
    # (30 + 10) * 34 / 64 s.
    finished = [(True, 30.0), (True, 30.0), (False, 2.0), (False, 2.0)]
    assert time_left(34.0, finished, 1, 5, []) == pytest.approx(40.0 * 34.0 / 64.0)
    # A rate from the finished tasks alone (tqdm's) would count every task as their
    # mean, 16 s: 6 * 16 * 34 / 64 = 51 s against 21.25 s.


def test_running_tasks_count_what_they_have_left_and_never_less_than_nothing():
    finished = [(True, 10.0), (False, 1.0)]
    # Running: a cold task 4 s in (6 s left of its 10) and a warm one past its mean.
    left = time_left(11.0, finished, 0, 0, [(True, 4.0), (False, 3.0)])
    assert left == pytest.approx(6.0 * 11.0 / 11.0)


def test_without_a_warm_task_finished_warm_ones_are_taken_as_long_as_cold_ones():
    assert time_left(20.0, [(True, 20.0)], 0, 2, []) == pytest.approx(40.0)
    assert time_left(4.0, [(False, 4.0)], 1, 0, []) == pytest.approx(4.0)


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_progress_counts_the_first_task_of_a_problem_and_method_as_cold():
    clock = Clock()
    keys = {0: ("pendulum", "rattle"), 1: ("pendulum", "rattle"), 2: ("andrews", "rattle"),
            -1: None}
    progress = Progress(4, None, keys=keys, clock=clock)
    assert progress._waiting() == (3, 1)  # the study, and each pair's first run
    progress.start(0, "pendulum / rattle h=0.1")
    clock.now = 10.0
    progress.finish(0, "ok", setup_s=8.0)
    assert progress._waiting() == (2, 1)  # the sweep's second run is warm
    assert progress.finished == [(True, 10.0)]
    assert progress.setup / progress.spent == pytest.approx(0.8)
    progress.start(1, "pendulum / rattle h=0.05")
    clock.now = 12.0
    progress.finish(1, "ok", setup_s=float("nan"))  # no set-up known: not in the share
    assert progress.finished[-1] == (False, 2.0) and progress.spent == 10.0
    # Two cold tasks left (the study, andrews): 2 * 10 s of work, done 12 s in 12 s.
    assert progress.left() == pytest.approx(20.0)


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_that_is_not_a_terminal_gets_plain_lines_and_no_bar():
    log = io.StringIO()
    progress = Progress(2, log, keys={0: "a", 1: "a"})
    assert progress.bar is None
    progress.start(0, "first")
    progress.finish(0, "first: ok", setup_s=1.0)
    progress.close()
    assert log.getvalue() == "[1/2] first: ok\n"


def test_a_terminal_gets_the_bar_with_the_estimate():
    clock = Clock()
    log = Terminal()
    progress = Progress(3, log, keys={0: "a", 1: "a", 2: "b"}, clock=clock)
    assert progress.bar is not None
    progress.start(0, "first")
    clock.now = 60.0
    progress.finish(0, "first: ok", setup_s=45.0)
    progress.close()
    text = log.getvalue()
    assert "[1/3] first: ok" in text and "1/3" in text
    # Left: one warm (taken as 60 s) and one cold task of 60 s, at the rate so far.
    assert "about 2 min left" in text and "set-up 75 % of run time" in text

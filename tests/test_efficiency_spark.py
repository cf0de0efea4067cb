"""The SPARK yardstick (``spark_lobatto3ab3.c``) ends where ``lobatto3ab3`` ends, and its
comparison in the efficiency benchmark gives rows of the shape the others give.

Timing is never asserted here (``python -m benchmarks.perf.efficiency`` measures it).
"""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

import integrators
from benchmarks.perf import efficiency
from benchmarks.perf.processes import YARDSTICKS, compile_yardstick
from integrators.tableau import lobatto
from helpers import IDA_KEYS, needs_cc


def test_spark_yardstick_has_the_suites_tableau():
    # The C source holds the coefficients as numbers; they must be lobatto3ab3's to the bit.
    source = (YARDSTICKS / "spark_lobatto3ab3.c").read_text()
    tab = lobatto(3)
    *_, B_inv = integrators.make("lobatto3ab3").tableau()
    for name, ours in (("C", tab.c), ("B", tab.b), ("A", tab.A), ("AH", tab.A_hat),
                       ("BINV", B_inv)):
        found = re.search(rf"static const double {name}\[S\](?:\[S\])? = (\{{.*?\}});",
                          source, re.S)
        assert found, name
        theirs = [float(x) for x in re.findall(r"[-+0-9.e]+", found.group(1))]
        assert theirs == np.ravel(ours).tolist(), name


@pytest.mark.slow
@needs_cc
def test_spark_yardstick_ends_where_lobatto3ab3_ends(tmp_path):
    # h = 0.003 does not divide t_end = 1: both must step on the suite's shrunk grid
    # (334 steps of 1/334). Iterating Newton to round-off under the same stopping rule,
    # the two end at round-off from each other, with Newton counts that differ only where
    # a rounding decides a stopping test.
    args = efficiency.parser().parse_args(["--t-end", "1", "--spark-h", "0.003",
                                           "--rounds", "1"])
    rows = efficiency.spark(args, tmp_path)
    assert [r["problem"] for r in rows] == ["pendulum", "sps-receiver"]
    for r in rows:
        assert IDA_KEYS <= set(r)
        assert r["family"] == "lobatto3ab3"
        assert r["steps"] == r["yardstick_steps"] == 334
        assert r["h"] == 1.0 / 334
        assert max(r["final_q_difference"], r["final_v_difference"]) <= 1e-12
        assert abs(r["newton"] - r["yardstick_newton"]) <= 0.01 * r["yardstick_newton"]
        assert r["yardstick_newton"] >= 2 * r["steps"]


@needs_cc
def test_spark_yardstick_rejects_a_bad_command_line(tmp_path):
    exe, note, _ = compile_yardstick("spark_lobatto3ab3", tmp_path)
    assert exe is not None, note
    done = subprocess.run([str(exe), "double-pendulum", "10", "0.01", "1e-16", "50", "1",
                           "1", "0", "0", "0"], capture_output=True, text=True)
    assert done.returncode == 2
    assert "usage:" in done.stderr and done.stdout == ""


@needs_cc
def test_spark_yardstick_fails_a_step_whose_newton_does_not_converge(tmp_path):
    # One Newton iteration cannot reach round-off: the step fails, with status 1.
    exe, note, _ = compile_yardstick("spark_lobatto3ab3", tmp_path)
    assert exe is not None, note
    done = subprocess.run([str(exe), "sps-receiver", "10", "0.01", "1e-16", "1", "1",
                           "1", "0.8", "0", "0"], capture_output=True, text=True)
    assert done.returncode == 1
    assert "Newton did not converge at step 1" in done.stderr


def test_spark_step_must_be_positive(capsys):
    with pytest.raises(SystemExit) as stop:
        efficiency.main(["--spark-h", "0"])
    assert stop.value.code == 2
    assert "--spark-h" in capsys.readouterr().err

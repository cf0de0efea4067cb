"""Where a set-up goes (:mod:`benchmarks.perf.compile_profile`): phases per program, CPU
time beside wall time, and the solves it is set against."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.perf.compile_profile import program_name

ROOT = Path(__file__).resolve().parent.parent


def test_a_programs_three_phases_go_under_one_name():
    assert program_name("run") == program_name("jit_run") == program_name("jit(run)") == "run"


@pytest.mark.slow
def test_the_profile_gives_each_programs_phases_and_the_cpu_time_of_set_up_and_solves(
        tmp_path):
    # A fresh process: the profile sets XLA's flags, which JAX reads once, at its start.
    out = tmp_path / "profile.json"
    done = subprocess.run([sys.executable, "-m", "benchmarks.perf.compile_profile",
                           "pendulum/rattle", "--solves", "2", "--json", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    (result,) = json.loads(out.read_text())
    assert result["pair"] == "pendulum/rattle" and "pendulum/rattle: case" in done.stdout
    assert set(result["phases_s"]) == {"trace", "lower", "xla"}
    run = result["programs_s"]["run"]  # the time loop, compiled afresh (the cache is off)
    assert run["trace"] > 0 and run["lower"] > 0 and run["xla"] > 0
    assert sum(result["phases_s"].values()) <= result["setup_wall_s"] * 1.01
    assert 0 < result["setup_cpu_s"] and 0 < result["solve_cpu_s"] < result["setup_cpu_s"]

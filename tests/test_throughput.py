"""The throughput benchmark against C (:mod:`benchmarks.perf.throughput`): its ratios over
the rounds, its reading of the waits for a core, its refusal of settings that time
nothing."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.perf.throughput import main, ratio_summary, run_queue_wait

ROOT = Path(__file__).resolve().parent.parent


def test_ratios_pair_the_rounds_and_the_fastest_rounds_apart():
    ours, theirs = [4.0, 9.0, 6.0, 8.0, 5.0], [8.0, 10.0, 6.0, 16.0, 10.0]
    ratio = ratio_summary(ours, theirs)
    assert ratio["per_round"] == [0.5, 0.9, 1.0, 0.5, 0.5]
    assert ratio["median"] == 0.5
    assert ratio["quartiles"] == (0.5, 0.9)
    # The fastest rounds need not be the same round: 9 / 16.
    assert ratio["fastest"] == 9.0 / 16.0


def test_one_round_is_its_own_median_and_quartiles():
    ratio = ratio_summary([3.0], [4.0])
    assert ratio["median"] == ratio["fastest"] == 0.75
    assert ratio["quartiles"] == (0.75, 0.75)


def test_the_wait_for_a_core_is_the_second_schedstat_field_summed_over_threads(tmp_path):
    # schedstat: time on a core, time runnable but waiting, timeslices (nanoseconds).
    for tid, line in (("101", "900000000 250000000 40\n"), ("102", "5 500000000 3\n")):
        (tmp_path / tid).mkdir()
        (tmp_path / tid / "schedstat").write_text(line)
    assert run_queue_wait(str(tmp_path)) == pytest.approx(0.75)
    (tmp_path / "102" / "schedstat").write_text("garbled\n")
    assert run_queue_wait(str(tmp_path)) is None
    assert run_queue_wait(str(tmp_path / "absent")) is None


@pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="Linux /proc only")
def test_the_wait_for_a_core_sums_this_processs_threads():
    before = run_queue_wait()
    end = time.process_time() + 0.05
    while time.process_time() < end:
        pass
    after = run_queue_wait()
    with open(f"/proc/self/task/{os.getpid()}/schedstat") as f:
        main_thread = int(f.read().split()[1]) * 1e-9
    assert 0.0 <= before <= after
    # The main thread's own count is part of the sum (read after it, so not above it).
    assert main_thread <= run_queue_wait()


@pytest.mark.parametrize("argv, named", [(["--rounds", "0"], "--rounds 0"),
                                         (["--steps", "0.5"], "--steps 0.5")])
def test_a_setting_that_times_nothing_is_one_line_and_status_2(argv, named, capsys):
    with pytest.raises(SystemExit) as ended:
        main(argv + ["--skip-memory"])
    assert ended.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and named in err and "at least 1" in err


@pytest.mark.slow
def test_the_report_gives_the_spread_and_the_waits():
    # A fresh process: the benchmark sets XLA's flags, which JAX reads once, at its start.
    done = subprocess.run([sys.executable, "-m", "benchmarks.perf.throughput", "--steps",
                           "2000", "--rounds", "3", "--skip-memory"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    if "no C compiler" in done.stdout:
        pytest.skip("no C compiler on PATH")
    assert "time loop compiled as one kernel: yes" in done.stdout
    for clock in ("wall clock", "CPU time"):
        assert f"ratio rattle / C by {clock}: " in done.stdout
        assert "median of 3 rounds; quartiles" in done.stdout
    assert "waiting for a core, share of the wall clock" in done.stdout
    assert "C and rattle agree: yes" in done.stdout

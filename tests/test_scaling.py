"""The scaling benchmark: its C yardsticks against rattle, the exponent fit, the bars, the
child processes (time limit, peak memory) and the command line."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import integrators
import problems
from benchmarks.perf import processes, scaling
from benchmarks.perf.scaling import C_NAME, Point, bars, fit_exponent
from benchmarks.executors import PLUGIN_ENV
from integrators.base import Grid

PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"


def compiled(name, tmp_path_factory):
    """The C yardstick ``name`` compiled as the benchmark compiles it (skip without a
    compiler; a failed build fails)."""
    exe, note, failed = processes.compile_yardstick(name, tmp_path_factory.mktemp("yardstick"))
    assert not failed, note
    if exe is None:
        pytest.skip(note)
    return exe


@pytest.fixture(scope="module")
def yardstick(tmp_path_factory):
    return compiled("rattle_chain", tmp_path_factory)


def test_c_yardstick_agrees_with_rattle_on_a_short_chain(yardstick):
    """300 steps of h = 1e-3 on chain:N=8 (0.3 s of the whip), the same step in C and JAX.

    Tolerances: both iterate Newton to the same test, so they differ only by the order of
    round-off; an O(eps) change of g per step moves the momenta by O(eps / h), which after
    300 steps was measured at 6e-16 in q and 1.3e-14 in v. 1e-13 and 1e-12 leave a margin
    of a hundred and stay far below what a change of the physics does (gravity off by
    0.1 % moves v by 3e-3 over 0.3 s).
    """
    N, steps, h = 8, 300, 1e-3
    out = subprocess.run([str(yardstick), str(N), str(steps), repr(h), "1e-16", "state"],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    head = out[0].split()
    q_c, v_c = np.array(out[1].split(), float), np.array(out[2].split(), float)
    case = problems.make(f"chain:N={N}").with_t_end(steps * h)
    # The dense path: Newton with the exact Jacobian at every iterate, as the C loop's.
    traj = integrators.make("rattle", h=h, linear_solver="dense").prepare(
        case, Grid(case.t0, case.t_end))()
    assert traj.status == "ok" and int(head[0]) == steps == traj.counts["n_steps"]
    assert np.max(np.abs(q_c - traj.q_final)) <= 1e-13
    assert np.max(np.abs(v_c - traj.v_final)) <= 1e-12
    # Both hold g and G v at round-off (coordinates O(0.1..1), eps = 2.2e-16).
    assert float(head[3]) <= 1e-15 and float(head[4]) <= 1e-15
    # |H - H0| (5e-6 here) moves by about 1e-10 of itself with the round-off above.
    energy = float(np.max(traj.windows["energy"]))
    assert abs(float(head[5]) - energy) <= 1e-6 * energy
    # The same Newton: the same iterations, up to a round-off tie in the stall test.
    assert abs(int(head[6]) - traj.counts["n_newton"]) <= 0.02 * traj.counts["n_newton"]


@pytest.fixture(scope="module")
def rigid_yardstick(tmp_path_factory):
    return compiled("rattle_rigid_chain", tmp_path_factory)


@pytest.mark.slow
def test_rigid_c_yardstick_agrees_with_rattle_s_structured_step(rigid_yardstick):
    """100 steps of h = 5e-4 on rigid-chain:N=4: the C program's closed-form mass inverse,
    kinetic-energy gradient, Jacobian and block Cholesky against rattle's structured path
    (autodiff, the whitened banded solver), the same simplified Newton.

    Measured apart: 8.9e-16 in q and 2.7e-15 in v, 530 against 539 Newton iterations (at
    the round-off floor the residual halves by chance, and the stopping rule then takes one
    more iteration, in either program). Gravity off by 0.1 % moves v by about 5e-7 here.
    """
    N, steps, h = 4, 100, 5e-4
    out = subprocess.run([str(rigid_yardstick), str(N), str(steps), repr(h), "1e-16", "state"],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    head = out[0].split()
    q_c, v_c = np.array(out[1].split(), float), np.array(out[2].split(), float)
    case = problems.make(f"rigid-chain:N={N}").with_t_end(steps * h)
    traj = integrators.make("rattle", h=h).prepare(case, Grid(case.t0, case.t_end))()
    assert traj.status == "ok" and traj.linear_solver != "dense"
    assert int(head[0]) == steps == traj.counts["n_steps"]
    assert np.max(np.abs(q_c - traj.q_final)) <= 1e-13
    assert np.max(np.abs(v_c - traj.v_final)) <= 1e-12
    assert float(head[3]) <= 1e-14 and float(head[4]) <= 1e-13
    energy = float(np.max(traj.windows["energy"]))
    assert abs(float(head[5]) - energy) <= 1e-6 * energy
    assert abs(int(head[6]) - traj.counts["n_newton"]) <= 0.05 * traj.counts["n_newton"]


@pytest.mark.parametrize("args", [["0", "1", "1e-3"], ["8", "1", "-1"], ["8", "x", "1e-3"],
                                  ["8", "1", "1e-3", "1e-16", "other"], ["8"]])
@pytest.mark.parametrize("program", ["yardstick", "rigid_yardstick"])
def test_c_yardsticks_refuse_bad_arguments(program, args, request):
    exe = request.getfixturevalue(program)
    done = subprocess.run([str(exe), *args], capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr.startswith("usage:")


def test_fit_exponent_recovers_a_power_law():
    ns = [64, 256, 1024, 4096, 16384]
    # Quadratic below N = 1024 and linear from it: the fit sees the large sizes only.
    costs = [1e-6 * n ** 2 if n < 1024 else 1e-3 * n for n in ns]
    slope, used = fit_exponent(ns, costs)
    assert used == [1024, 4096, 16384] and slope == pytest.approx(1.0, abs=1e-12)
    slope, used = fit_exponent(ns[:3], [2e-6 * n ** 1.5 for n in ns[:3]])
    assert used == [64, 256, 1024] and slope == pytest.approx(1.5, abs=1e-12)
    assert fit_exponent([64], [1.0]) == (None, [])
    assert fit_exponent([64, 256], [1.0, None]) == (None, [])


def _ok(problem, family, n, wall, rss=100 << 20, **extra):
    return Point(problem, n, family, "ok", steps=100, wall_per_step=wall, cpu_per_step=wall,
                 peak_rss=rss, **extra)


SETTINGS = {"problems": ["chain"], "steps": 100, "h": {"chain": 1e-5, "sps-ring": 1e-4},
            "rtol": 1e-8}


def _verdict(verdicts, start):
    return next(b for b in verdicts if b["bar"].startswith(start))


def test_bars_pass_fail_and_not_measured():
    points = [_ok("chain", C_NAME, 1024, 1e-5), _ok("chain", "rattle", 1024, 5e-5),
              _ok("chain", C_NAME, 16384, 1e-4), _ok("chain", "rattle", 16384, 2e-3),
              _ok("chain", "lobatto3ab3", 1024, 1e-3),
              Point("chain", 4096, "lobatto3ab3", "out of memory", "RESOURCE_EXHAUSTED"),
              Point("chain", 16384, "lobatto3ab3", "not run", "stopped at N=4096")]
    verdicts = bars(points, SETTINGS)
    ratio = _verdict(verdicts, "rattle / C time per step on chain:N=1024")
    assert ratio["verdict"] == "PASS" and ratio["value"].startswith("5 ")
    assert _verdict(verdicts, "rattle / C time per step on chain:N=16384")["verdict"] == "FAIL"
    # 2e-3 / 5e-5 = 40x growth against the 24x allowed.
    growth = _verdict(verdicts, "rattle on chain: time N=1024")
    assert growth["verdict"] == "FAIL" and growth["value"].startswith("40x")
    spark = _verdict(verdicts, "lobatto3ab3 finishes")
    assert spark["verdict"] == "FAIL" and "out of memory" in spark["value"]
    # A point that never ran fails its bar; one the options left out is not measured.
    assert _verdict(verdicts, "lobatto3ab3 on chain: time")["verdict"] == "FAIL"
    assert _verdict(verdicts, "baumgarte-rk4 on chain: time")["verdict"] == "NOT MEASURED"
    memory = _verdict(verdicts, "rattle on chain:N=16384: peak memory")
    assert memory["verdict"] == "PASS" and memory["value"] == "100 MiB"
    ring = _verdict(verdicts, "rattle on sps-ring:N=1024")
    assert ring["verdict"] == "NOT MEASURED"


def test_the_per_body_bar_is_read_against_plain_c():
    """The bar's verdict is rattle's own ratio; C's ratio of the same steps is given beside
    it, with whether the bar lies below what C reaches."""
    points = [_ok("chain", C_NAME, 16384, 1e-7), _ok("chain", "rattle", 16384, 3e-7),
              _ok("rigid-chain", C_NAME, 16384, 1.5e-6), _ok("rigid-chain", "rattle", 16384, 9e-6)]
    bar = _verdict(bars(points, SETTINGS), "rattle time per body on rigid-chain")
    assert bar["verdict"] == "FAIL" and bar["value"].startswith("30x")
    assert "plain C: 15x per body over per link (the bar is below what C reaches)" in bar["value"]
    assert "rattle over C 6x on the rigid chain and 3x on the chain" in bar["value"]
    points[2] = _ok("rigid-chain", C_NAME, 16384, 5e-7)
    bar = _verdict(bars(points, SETTINGS), "rattle time per body on rigid-chain")
    assert "plain C: 5x per body over per link, rattle" in bar["value"]
    # Without C's rigid-chain point, nothing is said about C.
    bar = _verdict(bars(points[:2] + points[3:], SETTINGS), "rattle time per body on rigid-chain")
    assert "plain C" not in bar["value"]


def test_a_ratio_measured_side_by_side_decides_its_bar():
    """Where the ratio was measured side by side in one process the bar reads it, with the
    separate processes' ratio beside it; where that measurement did not finish, the bar
    falls back to the separate processes and says why."""
    points = [_ok("chain", "rattle", 1024, 1e-4), _ok("chain", "rattle", 16384, 3e-3)]
    assert scaling.side_pairs({**SETTINGS, "families": ["rattle", "lobatto3ab3"]}, points) == [
        (("chain", 16384, "rattle"), ("chain", 1024, "rattle"))]
    side = {"num": ["chain", 16384, "rattle"], "den": ["chain", 1024, "rattle"],
            "status": "ok", "message": "", "rounds": 3, "ratio": 20.0, "ratio_min": 19.0,
            "ratio_max": 22.0, "ratio_cpu": 19.5}
    growth = _verdict(bars(points, SETTINGS, [side]), "rattle on chain: time")
    assert growth["verdict"] == "PASS" and growth["value"].startswith(
        "20x side by side in one process (median of 3 rounds, 19 to 22; by CPU time 19.5x)")
    assert "in separate processes 30x" in growth["value"]
    side.update(ratio=25.0)
    assert _verdict(bars(points, SETTINGS, [side]), "rattle on chain: time")["verdict"] == "FAIL"
    failed = {**side, "status": "timeout", "message": "killed at the limit of 600 s"}
    growth = _verdict(bars(points, SETTINGS, [failed]), "rattle on chain: time")
    assert growth["verdict"] == "FAIL" and growth["value"].startswith("30x")
    assert "side by side: timeout (killed at the limit of 600 s)" in growth["value"]
    # A ratio of other points is not this bar's.
    other = {**side, "ratio": 1.0, "den": ["chain", 4096, "rattle"]}
    assert _verdict(bars(points, SETTINGS, [other]), "rattle on chain: time")[
        "value"].startswith("30x")


@pytest.mark.slow
def test_a_ratio_side_by_side_alternates_both_points_in_one_process():
    """Two rounds of chain:N=8 over N=4 in one child: a finite ratio within its rounds'
    range; a side that fails its steps makes the pair ``failed`` with that side's message,
    as data."""
    from benchmarks.pool import thread_environment

    settings = {"h": {"chain": 0.05}, "steps": 5, "rtol": 1e-8, "newton_tol": 1e-16,
                "side_by_side": 2, "limit": 120.0}
    env = {**os.environ, **thread_environment()}
    side = scaling.run_pair(("chain", 8, "rattle"), ("chain", 4, "rattle"), settings, env)
    assert side["status"] == "ok" and side["rounds"] == 2, side
    assert 0 < side["ratio_min"] <= side["ratio"] <= side["ratio_max"] < 100
    failing = scaling.run_pair(("chain", 8, "rattle:newton_max_iter=1"), ("chain", 4, "rattle"),
                               settings, env)
    assert failing["status"] == "failed"
    assert failing["message"].startswith("rattle:newton_max_iter=1 on chain:N=8: failed:")


def test_a_growth_bar_says_what_more_newton_iterations_made_of_it():
    """The verdict is the time's growth; where the iterations per step changed with N the
    value gives both counts and the growth per iteration, and not otherwise."""
    points = [_ok("chain", "lobatto3ab3", 1024, 1e-3, newton_per_step=4.0),
              _ok("chain", "lobatto3ab3", 16384, 3e-2, newton_per_step=6.0),
              _ok("chain", "rattle", 1024, 1e-4, newton_per_step=4.0),
              _ok("chain", "rattle", 16384, 2e-3, newton_per_step=4.0)]
    growth = _verdict(bars(points, SETTINGS), "lobatto3ab3 on chain: time")
    assert growth["verdict"] == "FAIL" and growth["value"].startswith("30x")
    assert "Newton iterations per step 4 -> 6, time per iteration 20x" in growth["value"]
    growth = _verdict(bars(points, SETTINGS), "rattle on chain: time")
    assert growth["verdict"] == "PASS" and "Newton" not in growth["value"]


def test_ring_bar_needs_the_bound_on_g_and_the_minute():
    fine = dict(build_s=1.0, setup_s=5.0, first_solve_s=1.0)
    points = [_ok("sps-ring", "rattle", 1024, 1e-3, max_pos=1e-15, **fine),
              _ok("sps-ring", "lobatto3ab3", 1024, 1e-3, max_pos=1e-9, **fine),
              _ok("sps-ring", "baumgarte-rk4", 1024, 1e-3, build_s=1.0, setup_s=70.0,
                  first_solve_s=1.0)]
    verdicts = bars(points, {**SETTINGS, "problems": ["sps-ring"]})
    assert _verdict(verdicts, "rattle on sps-ring:N=1024")["verdict"] == "PASS"
    assert _verdict(verdicts, "lobatto3ab3 on sps-ring:N=1024")["verdict"] == "FAIL"
    assert _verdict(verdicts, "baumgarte-rk4 on sps-ring:N=1024")["verdict"] == "FAIL"
    assert _verdict(verdicts, "ida-ggl on sps-ring:N=1024")["verdict"] == "NOT MEASURED"
    other = bars(points, {**SETTINGS, "problems": ["sps-ring"], "steps": 20})
    assert _verdict(other, "rattle on sps-ring:N=1024")["verdict"] == "NOT MEASURED"


def test_a_process_past_its_limit_is_killed_and_reported():
    ending, _, _, _ = processes.run_process(
        [sys.executable, "-c", "import time; time.sleep(30)"], 0.5, dict(os.environ))
    assert ending == "timeout"


def test_peak_memory_is_the_program_s_own_not_its_parent_s():
    """A parent holding 200 MB starts a bare interpreter: ``ru_maxrss`` from ``wait4``
    would report at least 200 MB (Linux charges the parent's resident set at the exec);
    the program's own high-water mark is what a bare interpreter takes, tens of MB."""
    if processes.peak_rss() is None:
        pytest.skip("no /proc on this system")
    held = np.ones(200 << 17)  # 200 MiB, touched
    ending, out, _, _ = processes.run_process(
        [sys.executable, "-c",
         "from benchmarks.perf.processes import peak_rss; print(peak_rss())"],
        60.0, dict(os.environ))
    assert ending == "" and held.sum() > 0
    assert int(out.split()[-1]) < 100 << 20


@pytest.mark.slow
def test_like_a_worker_sets_xla_flags_only_before_the_first_computation(monkeypatch, capsys):
    """A fresh process gets the workers' flags (the one-kernel flag among them); one that
    has computed keeps its own, which XLA read at its start and the persistent cache's keys
    hash: changed, every later compilation of the process missed the cache. It says that
    its flags were left as they were."""
    from benchmarks import pool
    from integrators.loop import KERNEL_FLAG

    ending, out, _, _ = processes.run_process(
        [sys.executable, "-c", "import os; from benchmarks.perf.processes import like_a_worker; "
                               "like_a_worker(); print(os.environ['XLA_FLAGS'])"],
        120.0, {**os.environ, "XLA_FLAGS": ""})
    assert ending == "" and KERNEL_FLAG in out.split()
    flags = os.environ.get("XLA_FLAGS", "")
    for name in ("XLA_FLAGS", *pool.thread_environment()):  # restored after the test
        monkeypatch.setenv(name, os.environ.get(name, ""))
    assert KERNEL_FLAG not in flags.split()  # conftest: the tests compile without it
    processes.like_a_worker()
    assert os.environ["XLA_FLAGS"] == flags
    # ...and says so, since its timings are not a worker's.
    assert capsys.readouterr().err.startswith("note: XLA started before this process")


@pytest.mark.parametrize("argv", [["--n", "1"], ["--families", "no-such-method"],
                                  ["--h", "chain=-1"], ["--h", "pendulum=1e-3"],
                                  ["--limit", "0"], ["--steps", "0"], ["--rtol", "2"],
                                  ["--steps", "many"], ["--problems", "pendulum"],
                                  ["--processes", "0"], ["--side-by-side", "-1"]])
def test_bad_options_exit_2_with_one_line(argv, capsys):
    try:
        code = scaling.main(argv)
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_family_that_fails_stops_and_an_error_exits_1(tmp_path, monkeypatch, capsys):
    """Three families on chain:N=2 and 4: one finishes both, one fails its Newton (data: it
    stops, N=4 is not run), one raises (a defect: exit status 1)."""
    monkeypatch.setenv(PLUGIN_ENV, str(PLUGIN))
    # The baseline's process shows nothing of how families stop
    # (test_processes_run_each_point_in_rounds runs it).
    monkeypatch.setattr(scaling, "baseline_rss", lambda env: None)
    # Nothing here is timed: C runs once per point (microsecond runs would be started as
    # processes until they total MIN_TIMED, fifty of them).
    monkeypatch.setattr(scaling, "MIN_TIMED", 0.0)
    code = scaling.main(["--problems", "chain", "--n", "2", "4", "--steps", "5",
                         "--h", "chain=0.05", "--limit", "120", "--families", "rattle",
                         "rattle:newton_max_iter=1", "test-raise", "--repeats", "1",
                         "--out", str(tmp_path)])
    assert code == 1
    data = json.loads((tmp_path / "scaling.json").read_text())
    status = {(p["family"], p["n"]): p["status"] for p in data["points"]}
    assert status[("rattle", 2)] == status[("rattle", 4)] == "ok"
    assert status[("rattle:newton_max_iter=1", 2)] == "failed"
    assert status[("rattle:newton_max_iter=1", 4)] == "not run"
    assert status[("test-raise", 2)] == "error" and status[("test-raise", 4)] == "not run"
    if (C_NAME, 2) in status:
        assert all(a["agree"] for a in data["agreement"])
    for name in ("scaling.csv", "scaling.md", "scaling.html", "figures/scaling.svg"):
        assert (tmp_path / name).is_file()
    # N = 2 and 4 reach none of the bars' sizes: each is printed as not measured.
    out = capsys.readouterr().out
    assert "\nbars:\n" in out and "FAIL" not in out and "PASS" not in out


def test_each_point_is_its_median_process_and_the_ratio_to_c_that_of_the_medians():
    """Three rounds: each point is reported by its median process, with the fastest and
    slowest beside it; the ratio to C is recomputed from the medians; a point that failed
    in some round is reported as that round's."""
    rounds = [[_ok("chain", C_NAME, 64, c), _ok("chain", "rattle", 64, r, rss=k),
               _ok("chain", "lobatto3ab3", 64, 1.0) if k != 2 else
               Point("chain", 64, "lobatto3ab3", "timeout", "killed")]
              for k, (c, r) in enumerate([(1.0, 5.0), (2.0, 3.0), (1.5, 4.0)])]
    points = scaling.median_points(rounds)
    c, rattle, lobatto = points
    assert (c.wall_per_step, c.processes) == (1.5, 3)
    assert (rattle.wall_per_step, rattle.peak_rss) == (4.0, 2)   # the median process's own
    assert (rattle.wall_min_per_step, rattle.wall_max_per_step) == (3.0, 5.0)
    assert rattle.ratio_c == pytest.approx(4.0 / 1.5)
    assert lobatto.status == "timeout" and lobatto.processes is None
    # Even counts take the lower middle process.
    two = scaling.median_points([[_ok("chain", "rattle", 64, w)] for w in (2.0, 1.0)])
    assert two[0].wall_per_step == 1.0 and two[0].wall_max_per_step == 2.0


@pytest.mark.slow
def test_processes_run_each_point_in_rounds(tmp_path, capsys, monkeypatch):
    """``--processes 2`` runs every point twice in fresh processes and reports medians;
    the report says so."""
    # C's microsecond runs would be started as processes until they total MIN_TIMED (fifty
    # of them); one per point still gives each round its own time.
    monkeypatch.setattr(scaling, "MIN_TIMED", 0.0)
    code = scaling.main(["--problems", "chain", "--n", "2", "--steps", "5",
                         "--h", "chain=0.05", "--limit", "120", "--families", "rattle",
                         "--processes", "2", "--repeats", "1", "--out", str(tmp_path)])
    assert code == 0
    out = capsys.readouterr().out
    assert "round 1 of 2" in out and "round 2 of 2" in out
    data = json.loads((tmp_path / "scaling.json").read_text())
    assert data["settings"]["processes"] == 2
    for p in data["points"]:
        assert p["status"] == "ok" and p["processes"] == 2
        assert p["wall_min_per_step"] <= p["wall_per_step"] <= p["wall_max_per_step"]
    assert "each point in 2 fresh processes" in (tmp_path / "scaling.md").read_text()


@pytest.mark.slow
def test_the_report_gets_the_scaling_section(tmp_path, capsys):
    from dataclasses import asdict

    from benchmarks.store import Store
    from reports.__main__ import main as report_main

    points = [_ok("chain", C_NAME, 64, 3e-6), _ok("chain", "rattle", 64, 3e-4, ratio_c=100.0),
              _ok("chain", C_NAME, 256, 1.2e-5), _ok("chain", "rattle", 256, 1.1e-2),
              Point("chain", 256, "lobatto3ab3", "out of memory", "RESOURCE_EXHAUSTED <x>")]
    settings = {**SETTINGS, "n": [64, 256], "limit": 60.0, "memory_limit": 8 << 30,
                "c_yardstick": "cc -O2", "fit_from": 1024}
    data = {"settings": settings, "points": [asdict(p) for p in points],
            "fits": scaling.fits(points), "bars": bars(points, settings), "load": [1.0, 1.5],
            "baseline_rss": 200 << 20, "machine": {"cpus": 2}}
    folder = tmp_path / "scaling"
    folder.mkdir()
    (folder / "scaling.json").write_text(json.dumps(data))
    Store(tmp_path / "driftbench.sqlite").db.close()
    assert report_main(["--out", str(tmp_path), "--scaling", str(folder)]) == 0
    md = (tmp_path / "report.md").read_text()
    assert "## Scaling: cost per step against size" in md and "figures/scaling.svg" in md
    assert "RESOURCE_EXHAUSTED &lt;x>" in md
    html = (tmp_path / "report.html").read_text()
    assert html.count("<svg") == 1 and "<x>" not in html
    capsys.readouterr()
    assert report_main(["--out", str(tmp_path), "--scaling", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1

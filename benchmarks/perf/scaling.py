"""Benchmark: cost per step against system size, every family beside a plain-C O(N) RATTLE.

What runs
    Every family (default ``rattle``, ``lobatto3ab3``, ``baumgarte-rk4`` and ``ida-ggl``) on
    ``chain:N``, ``sps-ring:N`` (hub rows on), ``rigid-chain:N`` and ``four-bar:N`` for N =
    64, 256, 1024, 4096, 16384, each
    point in a fresh process, N ascending, the families of one N one after another so that
    a change in the machine's load hits them alike. Each point takes :data:`STEPS` steps of
    a fixed step size per problem (:data:`STEP_SIZES`); ``ida-ggl`` runs at rtol = atol =
    :data:`RTOL` over the same horizon and is measured per internal step. Both step sizes
    are stable at N = 16384 with a margin of two: the fastest motion of both systems grows
    like N (transverse waves along the links), so ``h N`` decides; 100 steps at N = 256
    with the ``h N`` of N = 16384 and with twice it finished with relative energy errors
    of at most 1.1e-4 (chain: ``baumgarte-rk4``, the explicit method; ring: ``rattle``
    and ``baumgarte-rk4``), and the C RATTLE ran 2000 steps of the chain at N = 16384 with
    ``h = 2e-5`` (at ``4e-5`` its Newton failed). ``lobatto3ab3`` was checked the same way
    on the chain at N = 16 only and not on the ring; ``ida-ggl`` chooses its own steps.

    ``rigid-chain:N`` (N rigid bodies in Euler parameters, a block-diagonal mass given by
    the kinetic energy: :mod:`linalg.blocks`) runs at ``h = 5e-4``. Its fastest motion
    grows like ``sqrt(N)``: the joint forces near the top carry the weight of the whole
    chain, about ``N m_b g_0``, against a body's moment of inertia of about 0.1 kg m^2 at
    lever 0.5 m, so ``omega`` is about ``sqrt(0.5 N m_b g_0 / 0.1)``, 900 rad/s at N =
    16384, and ``h omega`` about 0.45, inside RATTLE's and RK4's stability intervals with
    a margin of four or more (measured at N = 16384 over the 100 steps: max ``|H - H0|``
    at most 4.8e-7 against an energy scale of 1.3e9 for rattle, lobatto3ab3 and
    baumgarte-rk4; max ``|g|`` at most 3.1e-11 with coordinates of order 1e4). Per body, ``n = 7`` and ``m = 4`` against the chain's 2 and
    1 per link; the bars compare rattle's time per body with its time per link.

    ``four-bar:N`` (IFToMM A02: N parallelogram loops in natural coordinates, a constant
    banded mass; the augmented system's band ``L D L^T`` above
    :data:`linalg.schur.DENSE_KKT_MAX` constraints) runs at ``h = 1e-3``: the mechanism
    has one degree of freedom whatever N, so its motion does not speed up with N, and the
    100 steps end well before its first singular configuration (t = 0.72 s);
    ``python -m benchmarks.perf.four_bar`` runs it through them over the full 20 s.

    At each chain N the C yardstick ``benchmarks/perf/yardstick/rattle_chain.c`` runs the same
    steps: the RATTLE step of ``rattle`` for a separable Hamiltonian (exact Newton on the
    N multipliers with rattle's convergence test and tolerance, each iteration one
    tridiagonal Thomas solve; the velocity projection, another), and the same per-step
    measurement of ``|g|``, ``|G v|``, ``|H - H0|`` into per-window maxima. At each
    rigid-chain N ``yardstick/rattle_rigid_chain.c`` runs the step ``rattle`` takes there on
    its structured path (simplified Newton on ``(p_half, q_1, lambda)`` with ``S`` frozen at
    ``q_0``, rattle's stopping rule and tolerance, the velocity projection; ``M^{-1}``, ``T_q``
    and ``G`` in closed form, ``S`` factorised by 4 x 4 block Cholesky) with the same
    measurement: what the same arithmetic costs in plain C, against which the per-body bar
    can be read (:func:`bars`). Both are compiled here (``cc`` or ``gcc`` from ``PATH``,
    ``-O2``); without a compiler they are skipped with a message. ``rattle`` and C must end
    in the same state (:data:`AGREE_Q`, :data:`AGREE_V`, relative to the larger of 1 and the
    state's max-norm).

    Newton's tolerance on the chain is relative to the size of its constraints: ``g_k =
    |x_k - x_{k-1}|^2 - l^2`` with ``l = 1/N``, so rattle's absolute default of 1e-16 would
    be a relative 1e-16 N^2 (3e-8 at N = 16384), where two correct solvers that stop at
    different iterates differ by 1e-8 in the velocities. Every chain point (C and the
    fixed-step families) therefore takes ``newton_tol / N^2``, which iterates to round-off
    at every N.

What each number is
    time per step
        wall-clock (and CPU) time of ``solve()`` over the steps it took: the compiled time
        loop with its in-loop measurement and the read-back of the bounded trajectory (for
        ``ida-ggl``, IDA's one-step calls, our residual and Jacobian callbacks and the
        per-step recording: what running IDA costs here), divided by the accepted
        (internal) steps. Building the case, set-up and compilation are excluded and
        reported apart. C: its own clocks around its time loop. Both are the median of
        ``--repeats`` timed runs, more while they total less than :data:`MIN_TIMED`
        seconds (at most :data:`MAX_REPEATS`), fewer once they total
        :data:`REPEAT_BUDGET` seconds (:func:`more`). Each process is set up as the
        benchmark workers are, with one intra-op thread
        (:func:`benchmarks.perf.processes.like_a_worker`); C is single-threaded. Without
        the one-thread CPU client, XLA ran independent parts of a step on a second core:
        rattle on rigid-chain:N=16384 then took 3.7 us per body and step by the wall clock
        and 6.4 us of CPU time, against 5.7 to 6.0 us of either on one thread.
    Newton iterations per step
        the trajectory's ``n_newton`` over its steps (IDA: nonlinear iterations per
        internal step; ``baumgarte-rk4`` has none).
    peak memory
        the peak resident set of the point's whole process, from its start to its end
        (``VmHWM``, which the process reads from ``/proc`` at its end; for a process killed
        at the time limit the benchmark reads it just before the kill): interpreter, JAX,
        the case, compilation and the solves (:mod:`benchmarks.perf.processes` says why
        not ``ru_maxrss``). The same figure for a process that only imports the suite and
        computes once is printed as the baseline.
    linear solver
        ``Trajectory.linear_solver``, what the method says ran.
    Mflop
        the fixed-step loop's floating-point operations as XLA counts them in the
        compiled program (``compiled.cost_analysis()``), each loop body once, since XLA
        does not know how often a while loop runs: about one step with one Newton
        iteration and its recording. It says what a step's arithmetic is, not how much of
        it ran; the per-body bar gives the flop ratio and the time per Newton iteration
        ratio of rigid-chain and chain beside the time ratio.

With ``--processes K`` every point runs in ``K`` fresh processes, in ``K`` rounds over all
the points (each round as above), and the point reported is its median process: the one
whose time per step is the median (the lower of the two middle ones for even ``K``), with
the least and greatest time per step of the ``K`` beside it. On a shared machine the time
per step varies by a fifth or more from one process to the next (rigid-chain:N=16384,
rattle's step: 113 to 139 ms, each process's median, in six processes, load 1 to 2), and
the growth bar's ratio of two processes with it (20.1x to 27.8x in runs of one process per
point); a verdict should rest on the median of several interleaved processes. The ratio
to C is that of the two median processes. A point that is not ``ok`` in some round is
reported as that round's (the first such); a family that stopped in one round is not run
at that N or larger in later rounds.

The ratios of two points that the bars read (each family's growth from N = 1024 to 16384,
and rattle's time per body over its time per link) are measured side by side as well:
after the rounds, one fresh process per ratio prepares both points and solves them in
turn, ``--side-by-side K`` rounds (default :data:`SIDE_ROUNDS`; each side as often as
takes :data:`MIN_TIMED` s, the order swapped from one round to the next), and gives the
median over the rounds of each round's ratio of median times per step, with the least and
greatest. Both sides then run under the same load, which separate processes minutes apart
do not: rattle's growth on rigid-chain came to 28.9x as the ratio of two median processes
in a run whose load went from 0.8 to 1.1, and to 20.2x side by side in one process at load
0.9. A bar is judged on the side-by-side ratio where it finished, with the ratio of the
separate processes beside it; the per-point table, the fits and the memory bars stay those
of the separate processes. A side-by-side process runs under twice a point's time limit,
without the address-space cap (:func:`run_pair`).

A point runs under a time limit (``--limit``, default :data:`LIMIT` s for the whole process)
and an address-space cap (``--memory-limit``). A point that fails, runs out of time or out
of memory gets that status, and its family is not run at larger N on that problem (status
``not run``). The fitted exponent is the least-squares slope of log time per step against
log N over the finished points with N >= :data:`FIT_FROM` (all finished points if fewer
than two). The bars of the scaling issue are printed with PASS, FAIL or NOT MEASURED (a
point the options left out) and the measured number.

Writes ``scaling.json`` (settings, machine, load, points, fits, bars), ``scaling.csv``
(one row per point) and the report section (``scaling.md``, ``scaling.html``,
``figures/scaling.svg``; ``python -m reports --scaling DIR`` adds it to the main report)
under ``--out``. Exit status 1 only when something did not run as it should (a point that
errs for a reason other than time or memory, a C yardstick not compiling, C and rattle
disagreeing); a missed bar is not an error. Bad options: one line and exit status 2.

Usage::

    python -m benchmarks.perf.scaling
    python -m benchmarks.perf.scaling --n 64 256 --problems chain --families rattle --limit 30
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from benchmarks import compilation
from benchmarks.perf.processes import (compile_yardstick, like_a_worker, memory_exhausted,
                                       peak_rss, run_process, state_difference, timed_solve)
from benchmarks.records import EXIT_INPUT, CommandParser

FAMILIES = ("rattle", "lobatto3ab3", "baumgarte-rk4", "ida-ggl")
SIZES = (64, 256, 1024, 4096, 16384)
#: Fixed step per problem, stable at N = 16384 (module docstring).
STEP_SIZES = {"chain": 1e-5, "sps-ring": 1e-4, "rigid-chain": 5e-4, "four-bar": 1e-3}
STEPS = 100
#: Tolerance of the adaptive families (atol = rtol).
RTOL = 1e-8
#: Seconds per point, the whole process: lobatto3ab3 on rigid-chain:N=16384 takes 9 s (its
#: compiled loop in the cache) to about 50 s (compiled afresh) to set up and 72 to 93 s per
#: solve of 100 steps on one core of this shared machine, and ran past 120.
LIMIT = 300.0
#: Address-space cap per point (GiB): keeps a dense method from taking a shared machine's
#: memory; an idle process with JAX imported maps about 1.5 GiB.
MEMORY_LIMIT_GIB = 8.0
REPEATS = 3
#: Rounds of a ratio measured side by side (module notes).
SIDE_ROUNDS = 3
#: Short solves are repeated until they total this many seconds (at most MAX_REPEATS
#: times), so that one preemption does not decide a median of a few milliseconds.
MIN_TIMED, MAX_REPEATS = 0.2, 50
#: Timed solves stop once they total this many seconds.
REPEAT_BUDGET = 10.0
#: Smallest N of the exponent fit where at least two points reach it.
FIT_FROM = 1024
#: Agreement of C and rattle at the end of a run (max-norm, relative to the larger of 1 and
#: the state's max-norm: the rigid chain's coordinates grow like N). Both iterate Newton to
#: the same tolerance; on chain:N=8 over 300 steps of h = 1e-3 they end 6e-16 (q) and
#: 1.3e-14 (v) apart, on rigid-chain:N=1024 over 100 steps of 5e-4 8.1e-16 and 3.4e-13
#: relative. Gravity off by 0.1 % moves q by 5e-9 and v by 1e-5 over 100 steps of 1e-5.
AGREE_Q, AGREE_V = 1e-12, 1e-10
C_NAME = "C"
#: The C yardstick of each problem that has one, and the linear solver it runs.
C_YARDSTICKS = {"chain": ("rattle_chain", "tridiagonal (Thomas)"),
              "rigid-chain": ("rattle_rigid_chain", "block tridiagonal (4 x 4 block Cholesky)")}

#: The bars of the scaling issue.
RATIO_BAR, RATIO_SIZES = 10.0, (1024, 16384)
GROWTH_BAR, GROWTH_SIZES = 24.0, (1024, 16384)
SPARK_SIZE, SPARK_MEMORY, SPARK_RATIO, SPARK_STEPS = 4096, 2 << 30, 30.0, 100
RATTLE_MEMORY_SIZE, RATTLE_MEMORY = 16384, 2 << 30
RING_SIZE, RING_H, RING_STEPS, RING_RTOL = 1024, 1e-4, 100, 1e-8
RING_SECONDS, RING_POS = 60.0, 1e-10
#: rigid-chain: rattle's time per body at most this multiple of its time per link on the
#: chain, and every family's peak memory under RIGID_MEMORY, at RIGID_SIZE.
RIGID_SIZE, RIGID_PER_BODY, RIGID_MEMORY = 16384, 10.0, 2 << 30


@dataclass
class Point:
    """One family (or the C yardstick) on one problem at one N; None where not measured."""

    problem: str
    n: int
    family: str
    status: str
    message: str = ""
    steps: int | None = None
    rejected: int | None = None
    newton_per_step: float | None = None
    wall_per_step: float | None = None
    cpu_per_step: float | None = None
    ratio_c: float | None = None
    ratio_c_cpu: float | None = None
    repeats: int | None = None
    build_s: float | None = None
    setup_s: float | None = None
    first_solve_s: float | None = None
    process_s: float | None = None
    peak_rss: int | None = None
    max_pos: float | None = None
    max_vel: float | None = None
    max_energy: float | None = None
    linear_solver: str | None = None
    pattern_nnz: int | None = None
    flops: float | None = None
    processes: int | None = None
    wall_min_per_step: float | None = None
    wall_max_per_step: float | None = None


# --------------------------------------------------------------------------- one point

def more(times: list[float], repeats: int) -> bool:
    """Whether to time another run after ``times``: at least ``repeats``, more while they
    total under :data:`MIN_TIMED` s, at most :data:`MAX_REPEATS`, and none once they total
    :data:`REPEAT_BUDGET` s."""
    total = sum(times)
    return (len(times) < MAX_REPEATS and total < REPEAT_BUDGET
            and (len(times) < repeats or total < MIN_TIMED))


def prepare(spec: dict) -> tuple:
    """The prepared solve of the point ``spec`` describes, its building and its set-up
    seconds (in a process set up by :func:`like_a_worker`, the plugins loaded)."""
    import integrators
    import problems
    from integrators.base import Grid

    start = time.perf_counter()
    case = problems.make(f"{spec['problem']}:N={spec['n']}").with_t_end(
        spec["steps"] * spec["h"])
    integ = integrators.make(spec["family"], h=spec["h"], rtol=spec["rtol"],
                             newton_tol=spec["newton_tol"])
    build = time.perf_counter() - start
    # Two samples (start and end): the default 2000 sampled states would be the
    # harness's memory (0.5 GB at N = 16384), not the method's.
    grid = Grid(case.t0, case.t_end, n_samples=2)
    start = time.perf_counter()
    solve = integ.prepare(case, grid)
    return solve, build, time.perf_counter() - start


def capped(spec: dict) -> float:
    """Set the address-space cap of ``spec`` (before JAX is imported, so that every
    allocation, JAX's included, is under it); the monotonic deadline of its time limit."""
    if spec["memory_limit"]:
        resource.setrlimit(resource.RLIMIT_AS, (spec["memory_limit"],) * 2)
    return time.monotonic() + spec["limit"]


def point_main(argv: list[str]) -> int:
    """Child side of one point: ``argv[0]`` is its JSON settings; prints one JSON line."""
    spec = json.loads(argv[0])
    deadline = capped(spec)
    out: dict = {}
    try:
        like_a_worker()
        from benchmarks.executors import load_plugins

        load_plugins()
        solve, out["build_s"], out["setup_s"] = prepare(spec)
        walls, cpus = [], []
        while True:
            traj, wall, cpu, late = timed_solve(solve)
            walls.append(wall)
            cpus.append(cpu)
            out["setup_s"] += late
            # A margin of twice the last solve: a timing repeat must not turn a finished
            # point into a timeout.
            if (not more(walls, spec["repeats"])
                    or time.monotonic() + 2.0 * walls[-1] > deadline):
                break
        steps = traj.counts["n_steps"]
        out.update(
            status=traj.status, message=traj.message, steps=steps,
            rejected=traj.counts["n_rejected"], first_solve_s=walls[0], repeats=len(walls),
            newton_per_step=traj.counts["n_newton"] / steps if steps else None,
            wall_per_step=statistics.median(walls) / steps if steps else None,
            cpu_per_step=statistics.median(cpus) / steps if steps else None,
            **{f"max_{k}": float(np.max(traj.windows[k])) if len(traj.windows[k]) else None
               for k in ("pos", "vel", "energy")},
            linear_solver=traj.linear_solver, pattern_nnz=traj.pattern_nnz,
            flops=getattr(getattr(solve, "compiled", None), "flops", None))
        if spec.get("state"):
            np.save(spec["state"], np.concatenate([traj.q_final, traj.v_final]))
    except Exception as exc:  # recorded as the point's status, never fatal to the benchmark
        text = f"{type(exc).__name__}: {exc}"
        out.update(status="out of memory" if memory_exhausted(text) else "error",
                   message=" ".join(text.split())[:500])
    out["peak_rss"] = peak_rss()
    print(json.dumps(out))
    return 0


class Stopped(Exception):
    """A side of a ratio measured side by side that did not finish its steps."""


def pair_main(argv: list[str]) -> int:
    """Child side of a ratio measured side by side (module notes): ``argv[0]`` holds the
    settings of its two points, numerator first, and of the process; prints one JSON line.

    Each round solves both, the one first that went second in the round before, each as
    often as takes :data:`MIN_TIMED` s; a round's ratio is that of the two sides' median
    times per step in it. Rounds stop at ``rounds`` or once another would come within
    twice the last round's time of the limit.
    """
    spec = json.loads(argv[0])
    deadline = capped(spec)
    out: dict = {"status": "ok", "message": ""}
    try:
        like_a_worker()
        from benchmarks.executors import load_plugins

        load_plugins()
        solves = [prepare(side)[0] for side in spec["sides"]]
        ratios: dict[str, list[float]] = {"wall": [], "cpu": []}
        for r in range(spec["rounds"]):
            start = time.monotonic()
            rates = [{}, {}]
            for i in ((1, 0) if r % 2 == 0 else (0, 1)):
                walls, cpus = [], []
                while not walls or (sum(walls) < MIN_TIMED and len(walls) < MAX_REPEATS):
                    traj, wall, cpu, _ = timed_solve(solves[i])
                    if traj.status != "ok":
                        side = spec["sides"][i]
                        raise Stopped(f"{side['family']} on {side['problem']}:N={side['n']}: "
                                      f"{traj.status}: {traj.message}")
                    walls.append(wall / traj.counts["n_steps"])
                    cpus.append(cpu / traj.counts["n_steps"])
                rates[i] = {"wall": statistics.median(walls), "cpu": statistics.median(cpus)}
            for clock in ratios:
                ratios[clock].append(rates[0][clock] / rates[1][clock])
            if time.monotonic() + 2.0 * (time.monotonic() - start) > deadline:
                break
        out.update(rounds=len(ratios["wall"]), ratio=statistics.median(ratios["wall"]),
                   ratio_min=min(ratios["wall"]), ratio_max=max(ratios["wall"]),
                   ratio_cpu=statistics.median(ratios["cpu"]))
    except Stopped as exc:
        out.update(status="failed", message=" ".join(str(exc).split())[:500])
    except Exception as exc:  # recorded as the pair's status, never fatal to the benchmark
        text = f"{type(exc).__name__}: {exc}"
        out.update(status="out of memory" if memory_exhausted(text) else "error",
                   message=" ".join(text.split())[:500])
    print(json.dumps(out))
    return 0


CHILD = "import sys; from benchmarks.perf.scaling import point_main; sys.exit(point_main(sys.argv[1:]))"
PAIR_CHILD = CHILD.replace("point_main", "pair_main")


def newton_tol(problem: str, n: int, settings: dict) -> float | None:
    """Newton's tolerance at a point: relative to ``l^2 = 1/N^2`` on the chain (see above),
    the method's own elsewhere (None)."""
    return settings["newton_tol"] / n ** 2 if problem == "chain" else None


def point_spec(problem: str, n: int, family: str, settings: dict) -> dict:
    """What a child needs to build and prepare one point."""
    return {"problem": problem, "n": n, "family": family, "h": settings["h"][problem],
            "newton_tol": newton_tol(problem, n, settings), "steps": settings["steps"],
            "rtol": settings["rtol"]}


def run_child(code: str, spec: dict, env: dict) -> dict:
    """Run a child (``code`` with ``spec`` as its argument) under ``spec``'s time limit:
    its JSON result, or a ``status`` and ``message`` saying how it ended otherwise, with
    ``process_s`` and the ``peak_rss`` read while it ran (the child's own, where it gives
    one, is more exact)."""
    start = time.perf_counter()
    ending, stdout, stderr, rss = run_process([sys.executable, "-c", code, json.dumps(spec)],
                                              spec["limit"], env)
    out = {"status": "error", "process_s": time.perf_counter() - start, "peak_rss": rss}
    lines = stdout.strip().splitlines()
    if ending == "timeout":
        out.update(status="timeout", message=f"killed at the limit of {spec['limit']:g} s")
    elif ending == "killed by SIGKILL":
        out.update(status="out of memory", message="killed by SIGKILL from outside (the "
                                                   "out-of-memory killer, most likely)")
    elif ending or not lines:
        tail = " ".join(stderr.split())[-400:]
        out.update(status="out of memory" if memory_exhausted(stderr) else "error",
                   message=f"the process ended with {ending or 'no result'}: {tail}")
    else:
        out.update(json.loads(lines[-1]))
    return out


def run_family(problem: str, n: int, family: str, settings: dict, env: dict,
               state: Path | None = None) -> Point:
    """One point of a family in a fresh process."""
    spec = {**point_spec(problem, n, family, settings), "repeats": settings["repeats"],
            "limit": settings["limit"], "memory_limit": settings["memory_limit"],
            "state": str(state) if state else None}
    point = Point(problem, n, family, "error")
    for key, value in run_child(CHILD, spec, env).items():
        setattr(point, key, value)
    return point


def run_pair(num: tuple, den: tuple, settings: dict, env: dict) -> dict:
    """The ratio of two points' time per step, ``num`` and ``den`` each ``(problem, n,
    family)``, measured side by side in one fresh process (:func:`pair_main`) under twice
    a point's time limit.

    Without the address-space cap: both points finished under it in their own processes,
    and their pair needs no guard that they did not. With twice the cap, ida-ggl's pair
    of chain:N=1024 and 16384 ended in SuperLU's failed allocation all the same (its
    process resident at 1.0 GiB at most when uncapped): the two solvers' reserved address
    space, not their memory, exceeds it.
    """
    spec = {"sides": [point_spec(*num, settings), point_spec(*den, settings)],
            "rounds": settings["side_by_side"], "limit": 2.0 * settings["limit"],
            "memory_limit": 0}
    result = run_child(PAIR_CHILD, spec, env)
    return {"num": list(num), "den": list(den), **result}


def run_yardstick(exe: Path, problem: str, n: int, settings: dict
                  ) -> tuple[Point, np.ndarray | None]:
    """The C yardstick of ``problem`` at N, ``repeats`` runs; the point and its final
    ``(q, v)``."""
    h, steps = settings["h"][problem], settings["steps"]
    tol = newton_tol(problem, n, settings) or settings["newton_tol"]
    point = Point(problem, n, C_NAME, "ok", linear_solver=C_YARDSTICKS[problem][1])
    walls, cpus, state = [], [], None
    start = time.perf_counter()
    while more(walls, settings["repeats"]):
        first = not walls
        command = [str(exe), str(n), str(steps), repr(h), repr(tol)] + (["state"] if first
                                                                        else [])
        ending, stdout, stderr, _ = run_process(command, settings["limit"], dict(os.environ))
        if ending:
            # Exit status 1 is the yardstick's own failure report (Newton, a singular
            # factorisation, or no memory for the arrays); anything else (2: arguments it
            # refused, a signal) is a defect.
            point.status = ("timeout" if ending == "timeout" else
                            "out of memory" if memory_exhausted(stderr) else
                            "failed" if ending == "exit code 1" else "error")
            point.message = f"{ending}: {' '.join(stderr.split())[-400:]}"
            break
        lines = stdout.splitlines()
        head = lines[0].split()
        walls.append(float(head[1]))
        cpus.append(float(head[2]))
        point.steps = int(head[0])
        point.max_pos, point.max_vel, point.max_energy = map(float, head[3:6])
        point.newton_per_step = int(head[6]) / point.steps
        if int(head[7]) >= 0:
            point.peak_rss = max(point.peak_rss or 0, int(head[7]) * 1024)
        if first:
            state = np.concatenate([np.array(lines[1].split(), float),
                                    np.array(lines[2].split(), float)])
    point.process_s = time.perf_counter() - start
    if walls:
        point.repeats = len(walls)
        point.wall_per_step = statistics.median(walls) / point.steps
        point.cpu_per_step = statistics.median(cpus) / point.steps
    return point, state


def one_round(settings: dict, exes: dict, env: dict, tmp: Path,
              stopped: dict[tuple[str, str], Point]) -> tuple[list[Point], list[dict], bool]:
    """Every point once, each in a fresh process: the points (in one order every round),
    the agreements of C and rattle, and whether everything ran as it should. ``stopped``
    holds each ``(problem, family)``'s first point that was not ``ok``, over the rounds."""
    points, agreements, ok = [], [], True
    for problem in settings["problems"]:
        for n in settings["n"]:
            c_point = c_state = None
            if exes.get(problem) is not None:
                c_point, c_state = run_yardstick(exes[problem], problem, n, settings)
                points.append(c_point)
                ok &= c_point.status != "error"
            for family in settings["families"]:
                first = stopped.get((problem, family))
                if first is not None and n >= first.n:
                    points.append(Point(problem, n, family, "not run",
                                        f"stopped at N={first.n}: {first.status}"))
                    continue
                state = tmp / f"rattle-{problem}-{n}.npy" if c_state is not None \
                    and family == "rattle" else None
                point = run_family(problem, n, family, settings, env, state)
                points.append(point)
                print(f"  {problem}:N={n} {family}: {point.status}"
                      + (f", {_us(point.wall_per_step)} us/step"
                         if point.status == "ok" else f" ({point.message[:120]})"),
                      flush=True)
                ok &= point.status != "error"
                if point.status != "ok":
                    stopped[problem, family] = point
                if state is not None and point.status == "ok":
                    agree, dq, dv = agreement(c_state, np.load(state))
                    agreements.append({"problem": problem, "n": n, "agree": agree,
                                       "dq": dq, "dv": dv})
                    ok &= agree
    return points, agreements, ok


def median_points(rounds: list[list[Point]]) -> list[Point]:
    """Each point's median process over the rounds (module notes), with the spread of the
    time per step, and the ratios to C of the median processes."""
    out = []
    for same in zip(*rounds):
        bad = [p for p in same if p.status != "ok"]
        if bad:
            out.append(bad[0])
            continue
        ranked = sorted(same, key=lambda p: p.wall_per_step)
        point = ranked[(len(ranked) - 1) // 2]
        point.processes = len(same)
        point.wall_min_per_step = ranked[0].wall_per_step
        point.wall_max_per_step = ranked[-1].wall_per_step
        out.append(point)
    c = {(p.problem, p.n): p for p in out if p.family == C_NAME and p.status == "ok"}
    for p in out:
        mine = c.get((p.problem, p.n))
        if p.family != C_NAME and p.status == "ok" and mine is not None:
            p.ratio_c = p.wall_per_step / mine.wall_per_step
            p.ratio_c_cpu = p.cpu_per_step / mine.cpu_per_step
    return out


def baseline_rss(env: dict) -> int | None:
    """Peak resident set of a process that imports the suite and computes once (bytes)."""
    code = ("import jax, jax.numpy as jnp, integrators, problems; "
            "from benchmarks.perf.processes import peak_rss; "
            "jax.block_until_ready(jnp.ones(3) * 2.0); print(peak_rss())")
    ending, stdout, stderr, _ = run_process([sys.executable, "-c", code], LIMIT, env)
    if ending:
        raise RuntimeError(f"the baseline process ended with {ending}: {stderr[-400:]}")
    value = stdout.split()[-1]
    return None if value == "None" else int(value)


# --------------------------------------------------------------------------- analysis

def fit_exponent(ns, costs, from_n: int = FIT_FROM) -> tuple[float | None, list[int]]:
    """Least-squares slope of ``log cost`` against ``log N``, and the N it used.

    Uses the points with ``N >= from_n`` when there are at least two, else all points;
    ``(None, [])`` with fewer than two points. Non-positive or missing costs are ignored.
    """
    pairs = sorted((int(n), float(c)) for n, c in zip(ns, costs)
                   if c is not None and math.isfinite(c) and c > 0)
    large = [p for p in pairs if p[0] >= from_n]
    used = large if len(large) >= 2 else pairs
    if len(used) < 2 or len({n for n, _ in used}) < 2:
        return None, []
    x = np.log([n for n, _ in used])
    y = np.log([c for _, c in used])
    return float(np.polyfit(x, y, 1)[0]), [n for n, _ in used]


def fits(points: list[Point]) -> list[dict]:
    """The fitted exponent of time per step against N of every (problem, family)."""
    rows = []
    for problem, family in dict.fromkeys((p.problem, p.family) for p in points):
        done = [p for p in points if p.problem == problem and p.family == family
                and p.status == "ok"]
        slope, used = fit_exponent([p.n for p in done], [p.wall_per_step for p in done])
        rows.append({"problem": problem, "family": family, "exponent": slope, "n": used})
    return rows


def _find(points, problem, family, n) -> Point | None:
    return next((p for p in points if (p.problem, p.family, p.n) == (problem, family, n)),
                None)


def _verdict(name: str, held: bool | None, value: str) -> dict:
    return {"bar": name, "verdict": {True: "PASS", False: "FAIL", None: "NOT MEASURED"}[held],
            "value": value}


def _missing(point: Point | None, what: str) -> tuple[bool | None, str]:
    """The verdict of a bar whose point is not ``ok``: left out of the run is not measured;
    a point that did not finish fails the bar."""
    if point is None:
        return None, f"{what} is not in this run"
    return False, f"{what}: {point.status}" + (f" ({point.message})" if point.message else "")


def _ratio_bar(name: str, pair: tuple, labels: tuple[str, str], limit: float,
               unit: str = "", side: dict | None = None) -> dict:
    """A bar on ``pair[0]``'s time per step over ``pair[1]``'s (wall clock; the CPU-time
    ratio is given beside it): as measured side by side where ``side`` (:func:`run_pair`)
    is given and finished, the ratio of the two separate processes beside it; else that
    ratio."""
    # A point that did not finish fails the bar even where the other is left out.
    for p, label in sorted(zip(pair, labels), key=lambda x: x[0] is None):
        if p is None or p.status != "ok":
            return _verdict(name, *_missing(p, label))
    num, den = pair
    wall = num.wall_per_step / den.wall_per_step
    cpu = num.cpu_per_step / den.cpu_per_step
    apart = f"{wall:.3g}{unit} (by CPU time {cpu:.3g}{unit})"
    if side is None:
        return _verdict(name, wall <= limit, apart)
    if side["status"] != "ok":
        return _verdict(name, wall <= limit, f"{apart} in separate processes; side by side: "
                                             f"{side['status']} ({side['message']})")
    return _verdict(name, side["ratio"] <= limit,
                    f"{side['ratio']:.3g}{unit} side by side in one process (median of "
                    f"{side['rounds']} rounds, {side['ratio_min']:.3g} to "
                    f"{side['ratio_max']:.3g}; by CPU time {side['ratio_cpu']:.3g}{unit}); "
                    f"in separate processes {apart}")


def arithmetic(num: Point | None, den: Point | None) -> str:
    """What a time ratio of two finished points of one N is made of: their ratio of
    floating-point operations (XLA's count of each compiled loop, each loop body once: about
    a step with one Newton iteration) and of time per Newton iteration; empty where either
    is unknown."""
    if num is None or den is None or not (num.flops and den.flops and num.newton_per_step
                                           and den.newton_per_step):
        return ""
    flops = num.flops / den.flops
    return (f"; {flops:.3g}x the floating-point operations per pass through the loop "
            f"(XLA's count), {per_iteration(num, den):.3g}x the time per Newton iteration")


def per_iteration(num: Point, den: Point) -> float:
    """Ratio of two points' wall time per Newton iteration."""
    return ((num.wall_per_step / num.newton_per_step)
            / (den.wall_per_step / den.newton_per_step))


def iterations(num: Point | None, den: Point | None) -> str:
    """What a growth ratio of one family's finished points is made of where the number of
    Newton iterations per step changes with N (by 5 % or more): the two counts and the
    growth of the time per iteration, which is what the arithmetic of a step scales; empty
    otherwise."""
    if any(p is None or p.status != "ok" or not p.newton_per_step for p in (num, den)):
        return ""
    if abs(num.newton_per_step / den.newton_per_step - 1.0) < 0.05:
        return ""
    return (f"; Newton iterations per step {den.newton_per_step:.3g} -> "
            f"{num.newton_per_step:.3g}, time per iteration {per_iteration(num, den):.3g}x")


def in_c(rigid: tuple, c: tuple) -> str:
    """The per-body bar read against plain C: the C yardsticks' own ratio of time per body
    (rigid-chain) to time per link (chain) at the same N, and how far rattle is from C on
    each problem; empty where a point is missing."""
    if any(p is None or p.status != "ok" for p in (*rigid, *c)):
        return ""
    own = c[0].wall_per_step / c[1].wall_per_step
    return (f"; the same steps in plain C: {own:.3g}x per body over per link"
            + (" (the bar is below what C reaches)" if own > RIGID_PER_BODY else "")
            + f", rattle over C {rigid[0].wall_per_step / c[0].wall_per_step:.3g}x on the "
              f"rigid chain and {rigid[1].wall_per_step / c[1].wall_per_step:.3g}x on the chain")


def _memory_bar(name: str, point: Point | None, label: str, limit: int) -> dict:
    """A bar on a finished point's peak resident set."""
    if point is None or point.status != "ok":
        return _verdict(name, *_missing(point, label))
    if point.peak_rss is None:
        return _verdict(name, None, "no peak memory on this system (no /proc)")
    return _verdict(name, point.peak_rss < limit, f"{point.peak_rss / 2**20:.0f} MiB")


def side_pairs(settings: dict, points: list[Point]) -> list[tuple[tuple, tuple]]:
    """The ratios the bars read that are measured side by side as well (module notes):
    each family's growth on each problem and rattle's time per body over per link, each
    ``(numerator, denominator)`` of ``(problem, n, family)``, where both points finished."""
    lo, hi = GROWTH_SIZES
    pairs = [((problem, hi, family), (problem, lo, family))
             for problem in settings["problems"] for family in settings["families"]]
    pairs.append((("rigid-chain", RIGID_SIZE, "rattle"), ("chain", RIGID_SIZE, "rattle")))
    done = {(p.problem, p.n, p.family) for p in points if p.status == "ok"}
    return [pair for pair in pairs if pair[0] in done and pair[1] in done]


def _side(sides: list[dict], num: tuple, den: tuple) -> dict | None:
    return next((x for x in sides if (tuple(x["num"]), tuple(x["den"])) == (num, den)), None)


def bars(points: list[Point], settings: dict, sides: list[dict] = ()) -> list[dict]:
    """The bars of the scaling issue, each with PASS, FAIL or NOT MEASURED and its number;
    ``sides`` are the ratios measured side by side (:func:`run_pair`)."""
    out = []
    for n in RATIO_SIZES:
        out.append(_ratio_bar(
            f"rattle / C time per step on chain:N={n} <= {RATIO_BAR:g}",
            (_find(points, "chain", "rattle", n), _find(points, "chain", C_NAME, n)),
            (f"rattle at N={n}", f"C at N={n}"), RATIO_BAR))
    lo, hi = GROWTH_SIZES
    for problem in settings["problems"]:
        for family in settings.get("families", FAMILIES):
            per = " per internal step" if family == "ida-ggl" else ""
            pair = (_find(points, problem, family, hi), _find(points, problem, family, lo))
            bar = _ratio_bar(
                f"{family} on {problem}: time{per} N={lo} -> {hi} grows <= {GROWTH_BAR:g}x",
                pair, (f"{family} at N={hi}", f"{family} at N={lo}"), GROWTH_BAR, "x",
                _side(sides, (problem, hi, family), (problem, lo, family)))
            out.append({**bar, "value": bar["value"] + iterations(*pair)})
    spark = _find(points, "chain", "lobatto3ab3", SPARK_SIZE)
    name = (f"lobatto3ab3 finishes {SPARK_STEPS} steps of chain:N={SPARK_SIZE} with peak "
            f"memory < {SPARK_MEMORY / 2**30:g} GiB")
    if spark is not None and settings["steps"] != SPARK_STEPS:
        out.append(_verdict(name, None, f"this run takes {settings['steps']} steps"))
    else:
        out.append(_memory_bar(name, spark, f"lobatto3ab3 at N={SPARK_SIZE}", SPARK_MEMORY))
    out.append(_ratio_bar(
        f"lobatto3ab3 / rattle time per step on chain:N={SPARK_SIZE} <= {SPARK_RATIO:g}",
        (spark, _find(points, "chain", "rattle", SPARK_SIZE)),
        (f"lobatto3ab3 at N={SPARK_SIZE}", f"rattle at N={SPARK_SIZE}"), SPARK_RATIO))
    out.append(_memory_bar(
        f"rattle on chain:N={RATTLE_MEMORY_SIZE}: peak memory < {RATTLE_MEMORY / 2**30:g} GiB",
        _find(points, "chain", "rattle", RATTLE_MEMORY_SIZE), f"rattle at N={RATTLE_MEMORY_SIZE}",
        RATTLE_MEMORY))
    out.extend(ring_bars(points, settings))
    rigid = (_find(points, "rigid-chain", "rattle", RIGID_SIZE),
             _find(points, "chain", "rattle", RIGID_SIZE))
    bar = _ratio_bar(
        f"rattle time per body on rigid-chain:N={RIGID_SIZE} <= {RIGID_PER_BODY:g}x its time "
        f"per link on chain:N={RIGID_SIZE}", rigid,
        (f"rattle on rigid-chain at N={RIGID_SIZE}", f"rattle on chain at N={RIGID_SIZE}"),
        RIGID_PER_BODY, "x", _side(sides, ("rigid-chain", RIGID_SIZE, "rattle"),
                                   ("chain", RIGID_SIZE, "rattle")))
    c = (_find(points, "rigid-chain", C_NAME, RIGID_SIZE),
         _find(points, "chain", C_NAME, RIGID_SIZE))
    out.append({**bar, "value": bar["value"] + arithmetic(*rigid) + in_c(rigid, c)})
    for family in settings["families"] if "rigid-chain" in settings["problems"] else ():
        out.append(_memory_bar(
            f"{family} on rigid-chain:N={RIGID_SIZE}: peak memory < {RIGID_MEMORY / 2**30:g} GiB",
            _find(points, "rigid-chain", family, RIGID_SIZE), f"{family} at N={RIGID_SIZE}",
            RIGID_MEMORY))
    return out


def ring_bars(points: list[Point], settings: dict) -> list[dict]:
    """sps-ring:N=1024 (hub on): 100 steps of h = 1e-4 (ida-ggl at rtol 1e-8 over the same
    0.01 s), each ``ok`` within a minute (building, set-up and one solve), and max ``|g|``
    at most 1e-10 for rattle and lobatto3ab3."""
    out = []
    same = (settings["steps"] == RING_STEPS and settings["h"].get("sps-ring") == RING_H
            and settings["rtol"] == RING_RTOL)
    for family in FAMILIES:
        name = (f"{family} on sps-ring:N={RING_SIZE}: ok within {RING_SECONDS:g} s"
                + (f", max|g| <= {RING_POS:g}" if family in ("rattle", "lobatto3ab3") else ""))
        p = _find(points, "sps-ring", family, RING_SIZE)
        if p is not None and not same:
            out.append(_verdict(name, None, f"this run takes {settings['steps']} steps of "
                                            f"h = {settings['h'].get('sps-ring'):g}, rtol "
                                            f"{settings['rtol']:g}"))
        elif p is not None and p.status == "ok":
            seconds = p.build_s + p.setup_s + p.first_solve_s
            held = seconds <= RING_SECONDS
            value = f"{seconds:.3g} s (build {p.build_s:.2g}, set-up {p.setup_s:.2g}, solve " \
                    f"{p.first_solve_s:.2g})"
            if family in ("rattle", "lobatto3ab3"):
                held = held and p.max_pos <= RING_POS
                value += f", max|g| {p.max_pos:.2e}"
            out.append(_verdict(name, held, value))
        else:
            out.append(_verdict(name, *_missing(p, f"{family} at N={RING_SIZE}")))
    return out


def agreement(c_state: np.ndarray, rattle_state: np.ndarray) -> tuple[bool, float, float]:
    """Whether C and rattle end in the same ``(q, v)``; the two max-norm differences, each
    relative to the larger of 1 and C's max-norm of ``q`` (of ``v``)."""
    dq, dv = state_difference(c_state, rattle_state, relative=True)
    return dq <= AGREE_Q and dv <= AGREE_V, dq, dv


# --------------------------------------------------------------------------- output

def _us(x: float | None) -> str:
    return "-" if x is None else f"{1e6 * x:.4g}"


def _g(x: float | None, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def print_table(points: list[Point], problem: str) -> None:
    print(f"\n{problem}")
    print(f"  {'N':>6} {'family':<14} {'status':<13} {'steps':>5} {'us/step':>9} "
          f"{'cpu us':>9} {'x C':>7} {'Newton':>6} {'peak MiB':>8} {'set-up s':>8} "
          f"{'max|g|':>8} {'Mflop':>7}  linear solver")
    for p in (p for p in points if p.problem == problem):
        rss = "-" if p.peak_rss is None else f"{p.peak_rss / 2**20:.0f}"
        print(f"  {p.n:>6} {p.family:<14} {p.status:<13} {_g(p.steps, 'd'):>5} "
              f"{_us(p.wall_per_step):>9} {_us(p.cpu_per_step):>9} {_g(p.ratio_c):>7} "
              f"{_g(p.newton_per_step, '.2f'):>6} {rss:>8} {_g(p.setup_s, '.3g'):>8} "
              f"{_g(p.max_pos, '.1e'):>8} {_g(p.flops and p.flops / 1e6, '.3g'):>7}  "
              f"{p.linear_solver or '-'}")
        if p.status != "ok" and p.message:
            print(f"  {'':>6} {'':<14} {p.message[:160]}")


def write(out: Path, data: dict, points: list[Point]) -> list[Path]:
    """``scaling.json``, ``scaling.csv`` and the report section under ``out``."""
    from reports.scaling import write as write_section

    out.mkdir(parents=True, exist_ok=True)
    (out / "scaling.json").write_text(json.dumps(data, indent=1))
    with open(out / "scaling.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[x.name for x in fields(Point)])
        w.writeheader()
        w.writerows(asdict(p) for p in points)
    return [out / "scaling.json", out / "scaling.csv", *write_section(data, out)]


# --------------------------------------------------------------------------- driver


def parser() -> argparse.ArgumentParser:
    p = CommandParser(prog="python -m benchmarks.perf.scaling", description=__doc__.split("\n")[0])
    p.add_argument("--problems", nargs="+", default=list(STEP_SIZES), choices=list(STEP_SIZES),
                   help=f"problems (default: {' '.join(STEP_SIZES)})")
    p.add_argument("--n", nargs="+", type=int, default=list(SIZES),
                   help=f"sizes N (default: {' '.join(map(str, SIZES))})")
    p.add_argument("--families", nargs="+", default=list(FAMILIES),
                   help=f"integrator keys or specs (default: {' '.join(FAMILIES)})")
    p.add_argument("--steps", type=int, default=STEPS, help=f"steps per point (default {STEPS})")
    p.add_argument("--h", nargs="+", default=[], metavar="PROBLEM=H",
                   help="step size of a problem, e.g. chain=2e-5 (default: "
                        + " ".join(f"{k}={v:g}" for k, v in STEP_SIZES.items()) + ")")
    p.add_argument("--rtol", type=float, default=RTOL,
                   help=f"rtol = atol of adaptive families (default {RTOL:g})")
    p.add_argument("--limit", type=float, default=LIMIT,
                   help=f"seconds per point, whole process (default {LIMIT:g})")
    p.add_argument("--memory-limit", type=float, default=MEMORY_LIMIT_GIB,
                   help=f"address-space cap per point in GiB, 0 for none "
                        f"(default {MEMORY_LIMIT_GIB:g})")
    p.add_argument("--repeats", type=int, default=REPEATS,
                   help=f"timed solves per point, median reported (default {REPEATS})")
    p.add_argument("--processes", type=int, default=1,
                   help="fresh processes per point, in rounds over the points; the median "
                        "process is reported (default 1)")
    p.add_argument("--side-by-side", type=int, default=SIDE_ROUNDS, metavar="K",
                   help="rounds of each ratio the growth and per-body bars read, measured "
                        f"side by side in one process; 0 for none (default {SIDE_ROUNDS})")
    p.add_argument("--out", type=Path, default=Path("results/scaling"),
                   help="output folder (default: results/scaling)")
    return p


def settings_of(args) -> dict:
    """Checked settings from the parsed options; ``ValueError`` names a bad one."""
    if any(n < 2 for n in args.n):
        raise ValueError(f"--n {min(args.n)}: sizes must be at least 2 (the smallest ring)")
    for name, ok in (("steps", args.steps >= 1), ("repeats", args.repeats >= 1),
                     ("processes", args.processes >= 1), ("side-by-side", args.side_by_side >= 0),
                     ("limit", math.isfinite(args.limit) and args.limit > 0),
                     ("memory-limit", math.isfinite(args.memory_limit)
                      and args.memory_limit >= 0),
                     ("rtol", 0 < args.rtol < 1)):
        if not ok:
            value = getattr(args, name.replace("-", "_"))
            raise ValueError(f"--{name} {value:g}: out of range")
    steps = dict(STEP_SIZES)
    for item in args.h:
        problem, sep, value = item.partition("=")
        try:
            h = float(value)
        except ValueError:
            h = math.nan
        if not sep or problem not in STEP_SIZES or not (math.isfinite(h) and h > 0):
            raise ValueError(f"--h {item}: give PROBLEM=H with PROBLEM one of "
                             f"{', '.join(STEP_SIZES)} and H > 0")
        steps[problem] = h
    import integrators
    from problems.spec import SpecError, split_spec

    newton_tol = None
    for family in args.families:
        try:
            integ = integrators.make(family, h=steps["chain"], rtol=args.rtol)
        except SpecError as exc:
            raise ValueError(str(exc)) from None
        if split_spec(family)[0] == "rattle":
            newton_tol = integ.newton_tol
    if newton_tol is None:
        newton_tol = integrators.make("rattle").newton_tol
    return {"problems": list(dict.fromkeys(args.problems)), "n": sorted(set(args.n)),
            "families": list(dict.fromkeys(args.families)), "steps": args.steps, "h": steps,
            "rtol": args.rtol, "limit": args.limit,
            "memory_limit": int(args.memory_limit * 2**30), "repeats": args.repeats,
            "processes": args.processes, "side_by_side": args.side_by_side,
            "newton_tol": newton_tol}


def main(argv: list[str] | None = None) -> int:
    from benchmarks.executors import load_plugins
    from benchmarks.pool import thread_environment

    args = parser().parse_args(argv)
    compilation.enable()
    try:
        load_plugins()
        settings = settings_of(args)
    except ValueError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_INPUT
    env = {**os.environ, **thread_environment()}
    started = time.time()
    load_before = os.getloadavg()[0]
    ok = True
    agreements: list[dict] = []
    print(f"{settings['steps']} steps per point; h = "
          + ", ".join(f"{settings['h'][p]:g} ({p})" for p in settings["problems"])
          + f"; adaptive families at rtol = atol = {settings['rtol']:g} over the same horizon; "
            f"limit {settings['limit']:g} s per point (whole process); address-space cap "
            + (f"{args.memory_limit:g} GiB" if settings["memory_limit"] else "none"))
    print(f"1-minute load average {load_before:.2f} on {os.cpu_count()} cores (other processes "
          f"share them: read the times with it)")
    baseline = baseline_rss(env)
    print("baseline: a process that imports the suite and computes once peaks at "
          + ("? (no /proc)" if baseline is None else f"{baseline / 2**20:.0f} MiB resident"))
    with tempfile.TemporaryDirectory() as tmp:
        exes, notes = {}, {}
        for problem in settings["problems"]:
            if problem in C_YARDSTICKS:
                exes[problem], notes[problem], c_failed = compile_yardstick(
                    C_YARDSTICKS[problem][0], Path(tmp))
                print(f"C yardstick of {problem}: {notes[problem]}")
                ok &= not c_failed
        stopped: dict[tuple[str, str], Point] = {}
        rounds = []
        for r in range(settings["processes"]):
            if settings["processes"] > 1:
                print(f"round {r + 1} of {settings['processes']}", flush=True)
            measured, agreed, fine = one_round(settings, exes, env, Path(tmp), stopped)
            rounds.append(measured)
            agreements += agreed
            ok &= fine
        points = median_points(rounds)
    sides = []
    for num, den in side_pairs(settings, points) if settings["side_by_side"] else ():
        side = run_pair(num, den, settings, env)
        sides.append(side)
        ok &= side["status"] != "error"
        print(f"  side by side, {num[2]} on {num[0]}:N={num[1]} over {den[2]} on "
              f"{den[0]}:N={den[1]}: " + (f"{side['ratio']:.3g} (median of {side['rounds']} "
                                          f"rounds)" if side["status"] == "ok" else
                                          f"{side['status']} ({side['message'][:160]})"),
              flush=True)
    load_after = os.getloadavg()[0]
    for problem in settings["problems"]:
        print_table(points, problem)
    print("\nC and rattle at the end of each run with a C yardstick (max-norm relative to "
          f"max(1, |state|); agree when |dq| <= {AGREE_Q:g} and |dv| <= {AGREE_V:g}):")
    for a in agreements:
        print(f"  {a['problem']}:N={a['n']}: |dq| {a['dq']:.2e}, |dv| {a['dv']:.2e}: "
              f"{'agree' if a['agree'] else 'DISAGREE'}")
    if not agreements:
        print("  not compared (no finished pair)")
    fitted = fits(points)
    print(f"\nfitted exponent of time per step against N (least squares on log-log, "
          f"N >= {FIT_FROM} where two points reach it):")
    for f in fitted:
        exponent = "n/a (fewer than two finished points)" if f["exponent"] is None else \
            f"{f['exponent']:.2f} over N = {', '.join(map(str, f['n']))}"
        print(f"  {f['problem']:<11} {f['family']:<14} {exponent}")
    verdicts = bars(points, settings, sides)
    print("\nbars:")
    for b in verdicts:
        print(f"  {b['verdict']:<12} {b['bar']}: {b['value']}")
    print(f"\n1-minute load average {load_before:.2f} before, {load_after:.2f} after")
    data = {"settings": {**settings, "c_yardstick": "; ".join(
                f"{problem}: {note}" for problem, note in notes.items()) or "not used",
                         "fit_from": FIT_FROM},
            "machine": {"node": platform.node(), "cpus": os.cpu_count(),
                        "processor": platform.processor() or platform.machine(),
                        "python": platform.python_version()},
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)),
            "seconds": time.time() - started, "load": [load_before, load_after],
            "baseline_rss": baseline, "points": [asdict(p) for p in points],
            "agreement": agreements, "side_by_side": sides, "fits": fitted, "bars": verdicts}
    for path in write(args.out, data, points):
        print(f"wrote {path}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: ensembles in one compiled loop, against one trajectory at a time and plain C.

Rates
    For each method (``rattle``, ``lobatto3ab3``) and problem (``pendulum``, ``sps-receiver``)
    the same horizon (default ``1e4`` steps of ``h = 1e-2``) runs as one trajectory
    (:meth:`~integrators.base.Integrator.prepare`, the suite's single run) and as ensembles
    of ``K`` lanes (:meth:`~integrators.fixed.FixedStep.prepare_ensemble`, one compiled loop
    under ``jax.vmap``) from the problem's perturbed initial states
    (:mod:`problems.ensemble`), with the ensembles' recording grid
    (:data:`benchmarks.plan.ENSEMBLE_GRID`) on both. Each figure is a rate of steps: steps
    per second for one trajectory, lane-steps (lanes times steps) per second for an
    ensemble, timed around the whole ``solve()`` (the compiled loop and the read-back of
    the trajectories), after set-up and compilation, the median of ``--repeats`` solves. The
    C yardstick (``yardstick/rattle_sps.c``, the same RATTLE step on sps-receiver, see
    :mod:`benchmarks.perf.throughput`) gives plain C's steps per second beside them. This
    process is set up as the suite's workers are (one intra-op thread, the one-kernel XLA
    flag, :func:`benchmarks.perf.processes.like_a_worker`): one core.

    The bars (issue figures): at 1024 lanes on the pendulum, ``rattle``'s lane-steps per
    second at least :data:`BARS` ``["rattle"]`` times its one-trajectory steps per second,
    ``lobatto3ab3``'s at least ``BARS["lobatto3ab3"]`` times.

Memory
    ``rattle`` on ``chain:N=8`` with 16384 lanes, in fresh processes: the peak resident set
    (``VmHWM``) of the whole run (drawing the states, compiling, solving, reading back) at
    each of ``--memory-steps``. The loop keeps per lane only its state, the window maxima
    and three samples, so the peak must not grow with the steps; the bar is
    :data:`MEMORY_BAR` at ``1e5`` steps.

Figures and verdicts are printed; the exit status is 1 only when something did not run.

Usage::

    python -m benchmarks.perf.ensemble
    python -m benchmarks.perf.ensemble --lanes 1 256 1024 --skip-memory
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import integrators
import problems
from benchmarks.perf.processes import (compile_yardstick, like_a_worker, run_process)
from benchmarks.perf.throughput import run_c
from benchmarks.plan import ENSEMBLE_GRID
from benchmarks.records import CommandParser
from integrators.base import Grid
from problems.ensemble import draw

#: Lane-steps per second over one trajectory's steps per second, at :data:`BAR_LANES` lanes
#: on the pendulum.
BARS = {"rattle": 3.0, "lobatto3ab3": 2.0}
BAR_LANES = 1024
#: Peak resident set of the 16384-lane chain run (bytes).
MEMORY_BAR = 2 << 30


def timed(solve, repeats: int) -> tuple[float, object]:
    """Median seconds of ``repeats`` solves, and the last result."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = solve()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def rates(method: str, problem: str, steps: int, h: float, lanes: list[int], repeats: int,
          budget: float) -> dict:
    """One trajectory's steps per second and each ensemble's lane-steps per second; an
    ensemble expected to take longer than ``budget`` seconds per solve is skipped."""
    case = problems.make(problem).with_t_end(steps * h)
    grid = Grid(case.t0, case.t_end, **ENSEMBLE_GRID)
    integ = integrators.make(method, h=h)
    q0s, v0s = draw(case, max(lanes), seed=0)
    seconds, traj = timed(integ.prepare(case, grid), repeats)
    single = steps / seconds
    out = {"single": single, "lanes": {}}
    print(f"{method} on {problem}: one trajectory {single:.3g} steps/s "
          f"({traj.status}, {traj.counts['n_newton']} Newton iterations)", flush=True)
    for k in lanes:
        expected = k * steps / max(out["lanes"].values(), default=single)
        if expected > budget:
            print(f"  {k:6d} lanes: skipped (about {expected:.0f} s per solve, over the "
                  f"budget of {budget:g} s)", flush=True)
            continue
        start = time.perf_counter()
        solve = integ.prepare_ensemble(case, grid, q0s[:k], v0s[:k])
        setup = time.perf_counter() - start
        seconds, trajs = timed(solve, repeats)
        rate = k * steps / seconds
        out["lanes"][k] = rate
        bad = sum(t.status != "ok" for t in trajs)
        print(f"  {k:6d} lanes: {rate:.3g} lane-steps/s = {rate / single:.2f} x one "
              f"trajectory; solve {seconds:.3g} s, set-up {setup:.3g} s; {bad} lanes failed",
              flush=True)
    return out


CHILD = """
import json, sys, time
from benchmarks.perf.processes import like_a_worker, peak_rss
like_a_worker()
import integrators, problems
from benchmarks.plan import ENSEMBLE_GRID
from integrators.base import Grid
from problems.ensemble import draw
lanes, steps, h = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
case = problems.make("chain:N=8").with_t_end(steps * h)
q0s, v0s = draw(case, lanes, seed=0)
solve = integrators.make("rattle", h=h).prepare_ensemble(
    case, Grid(case.t0, case.t_end, **ENSEMBLE_GRID), q0s, v0s)
start = time.perf_counter()
trajs = solve()
print(json.dumps({"ok": sum(t.status == "ok" for t in trajs), "solve_s":
                  time.perf_counter() - start, "peak_rss": peak_rss()}))
"""


def memory(lanes: int, counts: list[int], h: float) -> bool:
    """Peak memory of the chain ensemble at each step count, in fresh processes."""
    print(f"\npeak memory of rattle on chain:N=8, {lanes} lanes, h = {h:g}, fresh processes:")
    peaks = []
    for steps in counts:
        command = [sys.executable, "-c", CHILD, str(lanes), str(steps), repr(h)]
        ending, stdout, stderr, polled = run_process(command, math.inf, None)
        if ending:
            print(f"  {steps:.0e} steps: ended with {ending}: {stderr.strip()[-500:]}")
            return False
        info = json.loads(stdout.strip().splitlines()[-1])
        peak = info["peak_rss"] or polled
        peaks.append(peak)
        print(f"  {steps:.0e} steps: peak RSS {peak / 2**20:.0f} MiB; {info['ok']} of {lanes} "
              f"lanes ok; solve {info['solve_s']:.1f} s "
              f"({lanes * steps / info['solve_s']:.3g} lane-steps/s)", flush=True)
    verdict = "holds" if max(peaks) < MEMORY_BAR else "NOT met"
    print(f"  under {MEMORY_BAR / 2**30:g} GiB at every step count: {verdict}")
    return True


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.ensemble",
                           description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=float, default=1e4, help="steps per run")
    parser.add_argument("--h", type=float, default=1e-2, help="step size")
    parser.add_argument("--lanes", type=int, nargs="+",
                        default=[1, 16, 256, 1024, 4096, 16384])
    parser.add_argument("--methods", nargs="+", default=list(BARS))
    parser.add_argument("--problems", nargs="+", default=["pendulum", "sps-receiver"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--budget", type=float, default=30.0,
                        help="seconds per solve above which an ensemble size is skipped")
    parser.add_argument("--memory-lanes", type=int, default=16384)
    parser.add_argument("--memory-steps", type=float, nargs="+", default=[1e3, 1e4, 1e5])
    parser.add_argument("--skip-memory", action="store_true")
    args = parser.parse_args(argv)
    load = like_a_worker()
    print(f"load average (1 min) at start: {load:.2f}")
    steps = int(args.steps)
    results = {(m, p): rates(m, p, steps, args.h, sorted(args.lanes), args.repeats,
                             args.budget)
               for p in args.problems for m in args.methods}
    with tempfile.TemporaryDirectory() as tmp:
        exe, note, _ = compile_yardstick("rattle_sps", Path(tmp))
        if exe is not None:
            c = run_c(exe, steps, args.h, 1e-16)
            print(f"\nC yardstick (RATTLE on sps-receiver, one trajectory): {c['rate']:.3g} "
                  f"steps/s")
        else:
            print(f"\nC yardstick: {note}")
    print("\nbars (pendulum, lane-steps/s over one trajectory's steps/s):")
    for method, bar in BARS.items():
        got = results.get((method, "pendulum"), {}).get("lanes", {}).get(BAR_LANES)
        if got is None:
            print(f"  {method}: not measured at {BAR_LANES} lanes")
            continue
        ratio = got / results[method, "pendulum"]["single"]
        print(f"  {method} at {BAR_LANES} lanes: {ratio:.2f} x (bar {bar:g} x): "
              f"{'holds' if ratio >= bar else 'NOT met'}")
    ok = True
    if not args.skip_memory:
        ok = memory(args.memory_lanes, [int(n) for n in args.memory_steps], args.h)
    print(f"load average (1 min) at end: {like_a_worker():.2f}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
